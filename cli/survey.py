"""``ra2vipas survey``: record a static scene swept over the full circle, and serve it as a rig
(``services/rigs/survey.py``; the format is docs/schemas/Survey.json)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from ra2vipas.cli.output import EXIT_USAGE, fail
from ra2vipas.cli.services import ConfigOpt, ConnectOpt, ListenOpt, LogOpt, ModeOpt, RigOpt, run_node, zenoh_settings

app = typer.Typer(help="Surveys: real data as a benchmark (record a static scene, serve it as a rig).", no_args_is_help=True)


@app.command("record")
def record(
    rig: Annotated[str, typer.Option("--rig", help="The live rig to drive through the sweep.")],
    output: Annotated[Path, typer.Option("--output", "-o", metavar="FILE", help="The survey file to write (JSON).")],
    pans: Annotated[int, typer.Option(min=4, max=100000, help="Evenly spaced pans per pass.")] = 180,
    passes: Annotated[int, typer.Option(min=1, max=1000, help="Sweeps over the full circle.")] = 3,
    n_train: Annotated[int, typer.Option("--n-train", min=0, max=100000, help="POD training samples to record (0: none).")] = 300,
    seed: Annotated[int, typer.Option(min=0, help="The episode seed (a simulated rig draws its scene from it).")] = 1,
    layout: Annotated[Optional[Path], typer.Option(metavar="FILE", help="The scene's layout, JSON {bearings_rad, ranges_m, tx_index} (a real scene; a simulated rig publishes its own).")] = None,
    overrides: Annotated[Optional[list[str]], typer.Option("--set", metavar="NAME=VALUE", help="Scenario parameter for a simulated rig's scene (repeatable), e.g. n_targets=8.")] = None,
    timeout: Annotated[float, typer.Option(min=0.5, help="How long to wait for one sample [s].")] = 10.0,
    mode: ModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None, zenoh_config: ConfigOpt = None,
) -> None:
    """Drive a live rig through PASSES sweeps of PANS pans (one fast episode: the scene must not
    move) and record every sample, its training stream and the layout, to a survey file."""
    from ra2vipas.cli.record import open_bus
    from ra2vipas.services.protocol.scenario import ScenarioError, build_scenario, parse_overrides
    from ra2vipas.services.rigs.survey import Layout, record_survey, save

    try:
        scenario = build_scenario("paper", parse_overrides(overrides or []))
    except ScenarioError as err:
        fail(str(err), EXIT_USAGE)
    scene = None
    if layout is not None:
        try:
            scene = Layout.model_validate_json(layout.read_bytes())
        except (OSError, ValueError) as err:
            fail(f"cannot read the layout {layout}: {str(err).splitlines()[0]}", EXIT_USAGE)
    bus = open_bus(mode, connect, listen, zenoh_config)
    try:
        survey = record_survey(bus, rig, pans=pans, passes=passes, n_train=n_train, seed=seed, layout=scene, timeout=timeout,
                               scenario=scenario)
    except RuntimeError as err:
        fail(str(err))
    finally:
        bus.close()
    try:
        save(survey, output)
    except OSError as err:
        fail(f"cannot write {output}: {err.strerror or err}")
    print(f"wrote a survey of {len(survey.layout.bearings_rad)} targets, {passes} passes of {pans} pans, "
          f"{len(survey.training)} training samples to {output}")


@app.command("serve")
def serve(
    file: Annotated[Path, typer.Argument(help="The survey file.")],
    rig: RigOpt = "survey-1",
    mode: ModeOpt = None, connect: ConnectOpt = None, listen: ListenOpt = None, zenoh_config: ConfigOpt = None,
    log_level: LogOpt = "INFO",
) -> None:
    """Serve a survey as a rig (kind survey): any commanded pan is answered from the nearest
    surveyed pan, passes drawn without replacement; the episodes' truth comes from its layout.
    Run a controller for the same rig (ra2vipas controller --rig NAME) and target it with
    campaign start --rig NAME --use-rig-values."""
    from ra2vipas.services.protocol.keys import check_chunk
    from ra2vipas.services.rigs.survey import SurveyNode, load
    from ra2vipas.services.transport.runtime import configure_logging

    configure_logging(log_level)
    try:
        check_chunk(rig, "rig")
        survey = load(file)
    except ValueError as err:
        fail(str(err), EXIT_USAGE)
    run_node(f"survey[{rig}]", zenoh_settings(mode, connect, listen, zenoh_config), lambda bus: SurveyNode(bus, rig, survey))
