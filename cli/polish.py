"""How the ``ra2vipas`` command line presents itself: help and usage errors.

* Help text is Markdown (``rich_markup_mode="markdown"``): paragraphs are reflowed to the
  terminal, whatever the line breaks of the docstring; an indented block is shown as it is
  (the examples).
* Flags show no ``<bool>`` value and usage lines name arguments as ``CAMPAIGN_ID``, not
  ``{campaign_id}`` (``polish``).
* A usage error (a value out of range, an unknown option, a missing argument) is one
  ``error: ...`` line on stderr and exit code 2, like every other error of the CLI (``run``).
* A renamed option keeps its old spelling as a hidden, deprecated alias (``deprecated``).
"""

from __future__ import annotations

import sys
from typing import Any, Optional

import typer
from typer import core as typer_core

MARKUP = "markdown"
INTERRUPTED = 130  # exit code of a command ended by Ctrl-C (128 + SIGINT)


def polish(command: Any) -> Any:
    """Walk a built click command tree: flags get an empty metavar (no ``<bool>``), arguments
    an upper-case usage name without braces. Returns ``command``."""
    for param in getattr(command, "params", ()):
        if isinstance(param, typer_core.TyperOption) and param.is_flag:
            param.metavar = ""
        elif isinstance(param, typer_core.TyperArgument):
            shown = param.metavar = (param.metavar or param.name or "").upper()
            usage = shown if param.required else f"[{shown}]"
            if param.nargs != 1 and not shown.endswith("..."):
                usage += "..."
            param._usage_display_name = (lambda text=usage: text)  # type: ignore[method-assign]
    help_option = command.get_help_option

    def get_help_option(ctx: Any) -> Any:  # --help is built per context, outside ``params``
        option = help_option(ctx)
        if option is not None:
            option.metavar = ""
        return option

    command.get_help_option = get_help_option
    for sub in getattr(command, "commands", {}).values():
        polish(sub)
    return command


def _markdown(app: typer.Typer) -> None:
    app.rich_markup_mode = MARKUP
    for group in app.registered_groups:
        if group.typer_instance is not None:
            _markdown(group.typer_instance)


def one_line(text: str) -> str:
    return " ".join(str(text).split())


def run(app: typer.Typer, argv: list[str] | None = None, prog_name: str = "ra2vipas") -> None:
    """Run ``app`` like ``app()``, but with ``polish`` applied and usage errors as one line."""
    try:
        from typer import _click  # the click that typer >= 0.2x vendors (its exceptions are not click's)
    except ImportError:  # pragma: no cover  (older typer: click itself)
        import click as _click

    _markdown(app)
    command = polish(typer.main.get_command(app))
    try:
        code = command.main(args=sys.argv[1:] if argv is None else argv, prog_name=prog_name, standalone_mode=False)
    except _click.exceptions.UsageError as err:
        where = f" (see `{err.ctx.command_path} --help`)" if err.ctx is not None else ""
        print(f"error: {one_line(err.format_message()).rstrip('.')}{where}", file=sys.stderr)
        sys.exit(err.exit_code)
    except _click.exceptions.ClickException as err:
        print(f"error: {one_line(err.format_message())}", file=sys.stderr)
        sys.exit(err.exit_code)
    except typer.Abort as err:
        if isinstance(err.__cause__, KeyboardInterrupt):  # click turns a Ctrl-C into Abort
            print("interrupted", file=sys.stderr)
            sys.exit(INTERRUPTED)
        print("error: aborted", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:  # a Ctrl-C while the command tree is built
        print("interrupted", file=sys.stderr)
        sys.exit(INTERRUPTED)
    sys.exit(code if isinstance(code, int) else 0)


def run_function(function: Any, prog_name: str) -> None:
    """``run`` for one command (a service's ``python -m ra2vipas.services.NAME``)."""
    app = typer.Typer(add_completion=False)
    app.command()(function)
    run(app, prog_name=prog_name)


def deprecated(old: str, new: str, **kw: Any) -> Any:
    """A hidden option spelled ``old`` (kept so that scripts keep working; use it in an
    ``Annotated[Optional[T], ...] = None`` parameter) whose value a command passes to ``prefer``."""
    return typer.Option(old, hidden=True, show_default=False, help=f"Deprecated spelling of {new}.", **kw)


def prefer(new_value: Any, old_value: Optional[Any], old: str, new: str) -> Any:
    """The value of a renamed option: the new spelling's, or, if only the old spelling was
    given, the old one's, with a one-line warning on stderr."""
    if old_value is None:
        return new_value
    print(f"warning: {old} is deprecated; use {new}", file=sys.stderr)
    return old_value
