"""The ``ra2vipas`` command line: one Typer app per command group, joined with ``add_typer``."""

from __future__ import annotations

import typer

from cli import bench, presets
from cli.simulate import simulate

app = typer.Typer(
    name="ra2vipas",
    help="Find which target around a pan camera carries the radio transmitter (Ra²ViPAS).",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
app.command("simulate")(simulate)
app.add_typer(presets.app, name="presets")
app.add_typer(bench.app, name="bench")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
