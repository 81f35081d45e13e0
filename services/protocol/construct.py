"""A cheaper ``model_construct`` for the messages built on a hot path: the measurement models
the simulator builds in its inner loop (a camera frame per frame, an RF pair and a step per
step, an advertisement per packet), and a rig's per-step ``Measurement`` and ``Command``.

``pydantic.BaseModel.model_construct`` walks every field (aliases, validation aliases, defaults
through ``get_default`` and ``smart_deepcopy``) on every call: ~6 us, ten times a step. ``builder``
checks once that a model needs none of that (no aliases, no post-init, extra not kept, every
default an immutable scalar or the empty tuple, which ``model_construct`` hands out as they are)
and returns a function that sets exactly what ``model_construct`` sets: ``__dict__`` with every
field in declaration order (the given values, the defaults for the rest), the set of the given
field names, no extra, no private attributes. Anything else falls back to ``model_construct``.
"""

from __future__ import annotations

from typing import Any, Callable

_SCALARS = (type(None), bool, int, float, str)


def builder(cls, *names: str) -> Callable[..., Any]:
    """``f(*values)`` = ``cls.model_construct(**dict(zip(names, values)))``, the same object (the
    fields are given positionally, in the order of ``names``)."""
    fields = cls.__pydantic_fields__
    plain = (set(names) <= set(fields) and len(set(names)) == len(names) and not cls.__pydantic_post_init__
             and not cls.__pydantic_root_model__ and cls.model_config.get("extra") != "allow")
    layout: list[tuple[str, int, Any]] = []  # (field, index into the values or -1, its default)
    for name, field in fields.items():
        if field.alias is not None or field.validation_alias is not None:
            plain = False
        if name in names:
            layout.append((name, names.index(name), None))
        elif field.is_required():
            plain = False
        else:
            default = field.get_default(call_default_factory=True, validated_data={})
            if not (type(default) in _SCALARS or default == () and type(default) is tuple):
                plain = False
            layout.append((name, -1, default))
    if not plain:
        def construct(*values):
            return cls.model_construct(**dict(zip(names, values)))
        return construct
    # generated once per (model, names): a dict display in field order, as fast as Python builds one
    args = ", ".join(f"v{i}" for i in range(len(names)))
    items = ", ".join(f"{name!r}: v{i}" if i >= 0 else f"{name!r}: d{k}" for k, (name, i, _) in enumerate(layout))
    given = ", ".join(repr(name) for name in names)
    source = (f"def construct({args}):\n"
              f"    m = new(cls)\n"
              f"    setattr_(m, '__dict__', {{{items}}})\n"
              f"    setattr_(m, '__pydantic_fields_set__', {{{given}}} if {len(names)} else set())\n"
              f"    setattr_(m, '__pydantic_extra__', None)\n"
              f"    setattr_(m, '__pydantic_private__', None)\n"
              f"    return m\n")
    namespace = {"new": cls.__new__, "cls": cls, "setattr_": object.__setattr__}
    namespace.update({f"d{k}": default for k, (_, i, default) in enumerate(layout) if i < 0})
    exec(source, namespace)
    return namespace["construct"]
