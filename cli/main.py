"""The ``ra2vipas`` command line: one Typer app per command group, joined with ``add_typer``."""

from __future__ import annotations

import typer

from ra2vipas.cli import bench, campaign, presets, protocol, radio, rigs, security, services, study, survey
from ra2vipas.cli.policies import policies
from ra2vipas.cli.record import record, replay
from ra2vipas.cli.rig import rig
from ra2vipas.cli.simulate import simulate
from ra2vipas.cli.up import up

app = typer.Typer(
    name="ra2vipas",
    help="Find which target around a pan camera carries the radio transmitter (Ra²ViPAS).",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        import ra2vipas

        print(f"ra2vipas {ra2vipas.__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print the version and exit.")) -> None:
    """Find which target around a pan camera carries the radio transmitter (Ra²ViPAS)."""


app.command("simulate")(simulate)
app.command("policies")(policies)
app.command("up")(up)
app.add_typer(campaign.app, name="campaign")
app.add_typer(study.app, name="study")
app.add_typer(rigs.app, name="rigs")
app.add_typer(presets.app, name="presets")
app.add_typer(bench.app, name="bench")
app.add_typer(protocol.app, name="protocol")
app.add_typer(security.app, name="security")
app.add_typer(survey.app, name="survey")
app.add_typer(radio.app, name="radio")
for _name in ("sensors", "controller", "learner", "orchestrator", "router"):
    app.command(_name)(getattr(services, _name))
app.command("rig")(rig)
app.command("record")(record)
app.command("replay")(replay)


def main() -> None:
    from ra2vipas.cli.polish import run

    run(app)


if __name__ == "__main__":
    main()
