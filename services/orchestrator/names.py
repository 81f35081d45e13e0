"""How tables, figures and the dashboard name and colour a pointing policy (issue 19).

Every list of policies here comes from the registry (``services/controller/registry.py``): the
built-ins (``registry.BUILTINS``) keep their paper labels and their colours, in their order;
any other name (a user's policy, installed or not where the results are read) is shown as it
is, in a colour chosen from its name, so the same policy has the same colour in every figure
and on every page, whatever it is drawn beside.
"""

from __future__ import annotations

import hashlib
from typing import Iterable

from ra2vipas.services.controller.registry import BUILTINS

BUILTIN_LABELS = ("Ra²ViPAS", "RaPAS", "RaViPAS", "sweep")
"""The paper's names of ``registry.BUILTINS``, in their order (Sec. IV-B; sweep is ours)."""
PLOT_COLOURS = ("C0", "C1", "C2", "C3")
"""Matplotlib's first four cycle colours, one per built-in in order (what a campaign of all
four drew before colours were assigned by name)."""
PLOT_EXTRA = ("C4", "C5", "C6", "C7", "C8", "C9")
"""Colours for any other policy in a matplotlib figure."""
WEB_COLOURS = ("#1f6fb4", "#d0402b", "#2b8f3a", "#8a5ac2")
"""The dashboard's colour of each built-in, in order."""
WEB_EXTRA = ("#b8860b", "#17a2b8", "#d45a9c", "#6b4f2a", "#7f7f7f", "#9aa31c")
"""The dashboard's colours for any other policy."""


def label(name: str, non_active: bool = False) -> str:
    """The paper's label of a built-in (``non_active``: sweep says it is non-active), else ``name``."""
    if name in BUILTINS:
        shown = BUILTIN_LABELS[BUILTINS.index(name)]
        return f"{shown} (non-active)" if non_active and name == "sweep" else shown
    return name


def _preferred(name: str, size: int) -> int:
    """A slot of a palette of ``size`` from the name alone (stable across processes, unlike ``hash``)."""
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "big") % size


def colours(names: Iterable[str], builtin: tuple[str, ...] = PLOT_COLOURS, extra: tuple[str, ...] = PLOT_EXTRA) -> dict[str, str]:
    """{name: colour} for the policies drawn together: a built-in's own colour; any other name
    the slot of ``extra`` its name picks, or, when a policy drawn beside it took that slot, the
    next free one (in the names' sorted order, so the same set always gets the same colours).
    Beyond ``len(extra)`` other policies, colours repeat."""
    names = list(dict.fromkeys(names))
    out = {n: builtin[BUILTINS.index(n)] for n in names if n in BUILTINS}
    taken: set[int] = set()
    for n in sorted(n for n in names if n not in BUILTINS):
        slot = _preferred(n, len(extra))
        for step in range(len(extra)):
            if (slot + step) % len(extra) not in taken:
                slot = (slot + step) % len(extra)
                break
        taken.add(slot)
        out[n] = extra[slot]
    return {n: out[n] for n in names}


def web_colours(names: Iterable[str]) -> dict[str, str]:
    """``colours`` in the dashboard's palette (CSS hex), what its charts draw each policy in."""
    return colours(names, WEB_COLOURS, WEB_EXTRA)
