"""The controller: measurements in, next pan and estimate out (paper Sec. III-B, and where it departs from the paper)."""

from __future__ import annotations

import ast
import json
import math
import pathlib
import subprocess
import sys
import typing

import numpy as np
import pydantic
import pytest

import ra2vipas.services as services
from ra2vipas.services.controller.policy import (
    ALGORITHMS,
    Controller,
    ControllerSettings,
    Decision,
    SensorConfig,
    sensor_config_from_scenario,
)
from ra2vipas.services.learner.pod import predict
from ra2vipas.services.orchestrator.metrics import associate
from ra2vipas.services.orchestrator.simulate import run_test, train_pod
from ra2vipas.services.protocol.measurements import CameraFrame, RFSample, StepMeasurement, TrainingSample
from ra2vipas.services.sensors import physics
from ra2vipas.services.sensors.world import SimulatedPlatform
from tests.conftest import (
    angle_error,
    make_platform,
    new_controller,
    polar_positions,
    run_closed_loop,
    run_open_loop,
    small_scenario,
    sweep_pans,
)

SERVICES = pathlib.Path(services.__file__).parent


def _layout(tx_deg: float):
    """Tx at 2.5 m and ``tx_deg``; five distractors, two of them within 15 degrees."""
    ranges = [2.5, 4.0, 5.0, 1.5, 3.8, 6.0]
    bearings = [tx_deg, tx_deg - 12.0, tx_deg + 15.0, tx_deg + 90.0, tx_deg - 150.0, tx_deg + 170.0]
    return polar_positions(ranges, bearings)


# -- 3. no ground truth reaches the controller ----------------------------------------------------


def _leaf_fields(model: type[pydantic.BaseModel], prefix: str = "") -> set[str]:
    out = set()
    for name, info in model.model_fields.items():
        ann = info.annotation
        args = typing.get_args(ann)
        if isinstance(ann, type) and issubclass(ann, pydantic.BaseModel):
            out |= _leaf_fields(ann, f"{prefix}{name}.")
        elif args and isinstance(args[0], type) and issubclass(args[0], pydantic.BaseModel):
            out |= _leaf_fields(args[0], f"{prefix}{name}[].")
        else:
            out.add(prefix + name)
    return out


def test_step_measurement_carries_only_sensor_readings():
    assert _leaf_fields(StepMeasurement) == {
        "step", "pan_rad", "rf[].iso_rssi_dbm", "rf[].dir_rssi_dbm", "frames[].box_bearings_rad",
        "frames[].box_heights_rad", "frames[].box_scores",  # since 1.3: what a detector says of each box
        "adverts[].receiver", "adverts[].rssi_dbm", "adverts[].channel", "adverts[].offset_s",  # since 1.3: the packets heard
        "adverts[].tag", "adverts[].address", "rf[].tag", "rf_tags[].tag", "rf_tags[].iso_rssi_dbm", "rf_tags[].dir_rssi_dbm",
        # since 1.4: which tag sent it (its advertiser address, which every packet carries), never who carries it
    }


def test_a_policys_episode_context_holds_nothing_of_the_world_it_will_search(small_pod):
    """What a policy gets when an episode starts (``contract.episode_context``: the rig's public
    description, the POD model, the public scenario, seed, test, early-decision level) is the same
    for two tests of one campaign, whose worlds (targets, Tx, walkers) differ: nothing in it comes
    from the world's draw. Only ``test`` differs."""
    import dataclasses

    from ra2vipas.services.controller.contract import EpisodeContext, episode_context
    from ra2vipas.services.controller.policy import sensor_config_from_scenario
    from ra2vipas.services.protocol.scenario import Scenario

    assert [f.name for f in dataclasses.fields(EpisodeContext)] == [
        "rig", "pod_model", "scenario", "seed", "test", "sensors", "stop_confidence"]
    scenario = small_scenario("dynamic")
    worlds = [SimulatedPlatform(scenario, 5, k).truth for k in (0, 1)]
    assert worlds[0].tx_index != worlds[1].tx_index or not np.allclose(worlds[0].bearings_rad, worlds[1].bearings_rad)
    a, b = (episode_context(sensor_config_from_scenario(scenario), small_pod.model, scenario, 5, k, 0.9) for k in (0, 1))
    assert set(a.scenario) == set(Scenario.model_fields)  # the parameters, nothing drawn
    assert dataclasses.replace(a, test=1) == b


def test_training_sample_carries_only_sensor_readings():
    assert _leaf_fields(TrainingSample) == {"index", "iso_rssi_dbm", "frames[].box_bearings_rad", "frames[].box_heights_rad",
                                            "frames[].box_scores", "adverts[].receiver", "adverts[].rssi_dbm",
                                            "adverts[].channel", "adverts[].offset_s", "adverts[].tag", "adverts[].address"}


def test_measurements_reject_extra_fields():
    rf = RFSample(iso_rssi_dbm=-40.0, dir_rssi_dbm=-38.0)
    with pytest.raises(pydantic.ValidationError):
        StepMeasurement(step=0, pan_rad=0.0, rf=rf, frames=(), tx_index=3)
    with pytest.raises(pydantic.ValidationError):
        CameraFrame(box_bearings_rad=(0.1,), target_ids=(4,))
    with pytest.raises(pydantic.ValidationError):
        RFSample(iso_rssi_dbm=-40.0, dir_rssi_dbm=float("nan"))


def test_sensor_config_describes_only_the_platform():
    assert {f for f in SensorConfig.__dataclass_fields__} == {
        "steps", "frames_per_rf", "fov_half_angle_rad", "box_bearing_noise_rad", "initial_pan_rad", "rssi_grows_with_alignment", "rf_period_s",
        "source", "rx_dir",  # where the description came from (descriptor | scenario) and the Rx(dir) response it names
        "rx_dir_curvature", "rx_dir_floor_db",  # that response's shape: the antenna's, a property of the platform
        "box_heights",  # whether the detector's boxes carry their angular heights (a property of the detector)
        "radio",  # what the receivers deliver: RSSI pairs or BLE advertisements (a property of the receivers)
    }
    sc = small_scenario(initial_pan_deg=45.0)
    cfg = sensor_config_from_scenario(sc)
    assert cfg.steps == 40 and cfg.frames_per_rf == 10
    assert cfg.fov_half_angle_rad == pytest.approx(math.pi / 8)
    assert cfg.box_bearing_noise_rad == pytest.approx(math.radians(0.25))
    assert cfg.initial_pan_rad == pytest.approx(math.pi / 4)
    assert cfg.rssi_grows_with_alignment is False
    assert sensor_config_from_scenario(small_scenario(antenna_model="db-gain")).rssi_grows_with_alignment is True


def test_controller_step_takes_a_step_measurement():
    hints = typing.get_type_hints(Controller.step)
    assert hints.pop("return") is Decision
    assert list(hints.values()) == [StepMeasurement]


def _imports(path: pathlib.Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                raise AssertionError(f"{path}: relative import")
            names.add(node.module or "")
            names |= {f"{node.module}.{a.name}" for a in node.names}
    return names



@pytest.mark.parametrize("package, allowed", [
    ("controller", ("ra2vipas.services.protocol", "ra2vipas.services.controller")),
    ("learner", ("ra2vipas.services.protocol", "ra2vipas.services.learner")),
])
def test_controller_and_learner_never_import_the_simulator(package, allowed):
    """Domain modules import only the protocol and their own package (never zenoh); the thin
    Zenoh adapters (node.py, __main__.py) may add the transport layer."""
    files = sorted((SERVICES / package).glob("*.py"))
    assert files
    adapters = {"node.py", "__main__.py"}
    for path in files:
        ok = allowed + (("ra2vipas.services.transport",) if path.name in adapters else ())
        for name in _imports(path):
            assert not name.startswith("ra2vipas.services.sensors"), f"{path.name} imports {name}"
            assert not name.startswith("ra2vipas.services.orchestrator"), f"{path.name} imports {name}"
            if path.name not in adapters:
                assert not name.startswith("zenoh"), f"domain module {path.name} imports {name}"
            if name.startswith(("ra2vipas.services", "ra2vipas.cli")):
                assert name.startswith(ok), f"{path.name} imports {name}"


def _named_modules(path: pathlib.Path) -> set[str]:
    """Modules a file names in a string: code it runs in a child process (``python -c``) or
    imports by name (``importlib.import_module``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    return {node.value for node in ast.walk(tree) if isinstance(node, ast.Constant) and isinstance(node.value, str)}


def test_the_services_never_import_the_cli():
    """The services layer imports nothing of the command line (the CLI builds on the services,
    never the other way round): the `python -m ra2vipas.services.NAME` entries and the
    benchmarks (services/benchmarks/, which the CLI hands a stack launcher instead) included,
    and neither in a child process's code nor by a module name in a string."""
    files = sorted(SERVICES.rglob("*.py"))
    assert any(path.parent.name == "benchmarks" for path in files)
    for path in files:
        rel = path.relative_to(SERVICES).as_posix()
        for name in _imports(path):
            assert not name.startswith("ra2vipas.cli"), f"{rel} imports {name}"
        for text in _named_modules(path):
            assert "ra2vipas.cli" not in text, f"{rel} names the CLI in {text!r}"


def _imported_by(modules: str, which: str, then: str = "") -> list[str]:
    """The modules (``which``: a condition on a module name ``m``) that importing ``modules`` (a
    comma-separated list), and running the statement ``then`` after, loads in a fresh interpreter."""
    code = f"import json, sys, {modules}; {then or 'pass'}; print(json.dumps(sorted(m for m in sys.modules if {which})))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=SERVICES.parent)
    return json.loads(out.stdout)


def test_controller_and_learner_load_without_the_simulator():
    assert _imported_by("ra2vipas.services.controller.policy, ra2vipas.services.learner.pod",
                        "m.startswith(('ra2vipas.services.sensors', 'ra2vipas.services.orchestrator'))") == []


def test_the_orchestrator_starts_without_the_controllers_the_learners_fit_or_numba():
    """The orchestrator scores a learner's model (``learner/trained.py``) and reduces episodes; it
    runs no policy and fits nothing, so its start imports neither the controllers' code, nor the
    learner's fit, nor numba or SciPy (~0.3 s of CPU at every start)."""
    assert _imported_by("ra2vipas.services.orchestrator.api.app",
                        "m.split('.')[0] in ('numba', 'scipy', 'sklearn') or m in ('ra2vipas.services.controller.policy', "
                        "'ra2vipas.services.learner.pod', 'ra2vipas.services.orchestrator.simulate', "
                        "'ra2vipas.services.sensors.world')") == []


def test_the_orchestrator_finishes_and_serves_a_campaign_without_the_simulator_or_the_controllers():
    """Its results object (``reduce.results_object``: the envelope, the below-chance warning that
    names the built-ins reading Rx(dir)) and a results page's overrides come from modules that
    import neither the simulator nor a controller (~1 s of CPU at an orchestrator's first campaign
    end, while the rigs of the next one run)."""
    finish = ("from ra2vipas.services.orchestrator import envelope, rigcheck; "
              "rigcheck.dr_warnings({'scenario': {'n_targets': 20}, 'tests': 200, 'algorithms': {'rapas': {'dr_final': 0.0}}}); "
              "envelope.overrides_of('paper', {'n_targets': 8})")
    assert _imported_by("ra2vipas.services.orchestrator.api.app, ra2vipas.services.orchestrator.reduce",
                        "m.split('.')[0] == 'numba' or m in ('ra2vipas.services.controller.policy', "
                        "'ra2vipas.services.controller.builtins', 'ra2vipas.services.orchestrator.simulate')", finish) == []


def test_the_orchestrator_a_learner_and_a_rig_start_without_the_fitting_and_plotting_libraries():
    """What only a fit, an assignment or a figure uses is imported by it: the orchestrator's API, a
    learner with nothing to fit and a rig start without scikit-learn, scipy.optimize/stats and
    matplotlib (~3 s of CPU at every start of a stack's processes)."""
    assert _imported_by("ra2vipas.services.orchestrator.api.app, ra2vipas.services.learner.node, "
                        "ra2vipas.services.controller.node, ra2vipas.services.sensors.node",
                        "m.startswith(('sklearn', 'matplotlib', 'scipy.optimize', 'scipy.stats', 'pandas'))") == []


# -- interface ----------------------------------------------------------------------------------------


def test_settings_are_validated():
    bads = ({"beta": -1.0}, {"grid_points": 8}, {"lobe_width_rad": 0.0}, {"residual_length_scale_rad": -1.0}, {"probe_every": -1})
    for bad in bads:
        with pytest.raises(ValueError):
            ControllerSettings(**bad)
    with pytest.raises(ValueError):
        Controller("simulated-annealing", sensor_config_from_scenario(small_scenario()), None)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_decisions_are_angles_on_the_circle(algorithm, small_pod):
    sc = small_scenario(initial_pan_deg=170.0)
    c = new_controller(algorithm, sc, small_pod.model)
    assert c.first_pan() == pytest.approx(math.radians(170.0))
    decisions = run_closed_loop(c, SimulatedPlatform(sc, 3, 0), sc.steps)
    for t, d in enumerate(decisions):
        assert d.step == t
        assert -math.pi <= d.next_pan_rad < math.pi
        assert -math.pi <= d.estimate_rad < math.pi
        assert math.isfinite(d.reward)


def test_same_measurements_same_decisions(small_pod):
    sc = small_scenario()
    a, b = new_controller("ra2vipas", sc, small_pod.model), new_controller("ra2vipas", sc, small_pod.model)
    da = run_closed_loop(a, SimulatedPlatform(sc, 8, 1), sc.steps)
    db = run_closed_loop(b, SimulatedPlatform(sc, 8, 1), sc.steps)
    assert da == db


def test_sweep_pans_evenly(small_pod):
    sc = small_scenario(initial_pan_deg=-90.0)
    decisions = run_closed_loop(new_controller("sweep", sc, small_pod.model), SimulatedPlatform(sc, 0, 0), sc.steps)
    for t, d in enumerate(decisions):
        assert angle_error(d.next_pan_rad, -math.pi / 2 + 2 * math.pi * (t + 1) / sc.steps) < 1e-9
        assert not d.probe


def test_warmup_sees_every_bearing_once(small_pod):
    sc = small_scenario(initial_pan_deg=30.0)
    decisions = run_closed_loop(new_controller("ra2vipas", sc, small_pod.model), SimulatedPlatform(sc, 0, 0), sc.steps)
    warmup = math.ceil(math.pi / sc.fov_half_angle_rad)
    pans = [sc.initial_pan_rad] + [d.next_pan_rad for d in decisions[: warmup - 1]]
    for t, pan in enumerate(pans):
        assert angle_error(pan, sc.initial_pan_rad + 2 * math.pi * t / warmup) < 1e-9
    # the warm-up pans' fields of view cover the whole circle
    covered = np.zeros(360, dtype=bool)
    for pan in pans:
        covered |= np.abs(physics.wrap(np.radians(np.arange(360)) - pan)) <= sc.fov_half_angle_rad + 1e-9
    assert covered.all()


def _strip(m: StepMeasurement, frames=None, dir_rssi=None) -> StepMeasurement:
    rf = RFSample(iso_rssi_dbm=m.rf.iso_rssi_dbm, dir_rssi_dbm=m.rf.dir_rssi_dbm if dir_rssi is None else dir_rssi)
    return StepMeasurement(step=m.step, pan_rad=m.pan_rad, rf=rf, frames=m.frames if frames is None else frames)


def test_rapas_ignores_the_camera_and_ravipas_ignores_rx_dir(small_pod):
    sc = small_scenario()
    platform = SimulatedPlatform(sc, 5, 0)
    ms = [platform.sense(t, p) for t, p in enumerate(sweep_pans(sc.steps))]
    blind = [_strip(m, frames=tuple(CameraFrame() for _ in m.frames)) for m in ms]
    deaf = [_strip(m, dir_rssi=-60.0) for m in ms]
    ctl = lambda a: new_controller(a, sc, small_pod.model)  # noqa: E731
    c1, c2 = ctl("rapas"), ctl("rapas")
    assert [c1.step(m) for m in ms] == [c2.step(m) for m in blind]
    c1, c2 = ctl("ravipas"), ctl("ravipas")
    assert [c1.step(m) for m in ms] == [c2.step(m) for m in deaf]
    # ... while ra2vipas uses both
    c1, c2 = ctl("ra2vipas"), ctl("ra2vipas")
    assert [c1.step(m) for m in ms] != [c2.step(m) for m in blind]


# -- 1. the fused objective peaks at the Tx bearing ----------------------------------------------------


@pytest.mark.parametrize("model", ["paper", "db-gain"])
@pytest.mark.parametrize("tx_deg", [30.0, -100.0, 179.0, -179.0])
def test_sweep_estimate_and_reward_peak_at_the_tx(model, tx_deg, paper_pod):
    sc = small_scenario(steps=144, antenna_model=model, n_targets=6)
    platform = make_platform(sc, _layout(tx_deg), tx_index=0, seed=1)
    pans = sweep_pans(72, rounds=2)
    decisions = run_open_loop(new_controller("ra2vipas", sc, paper_pod.model), platform, pans)
    tx = platform.truth.tx_bearing_rad
    est = decisions[-1].estimate_rad
    assert associate(np.array([est]), platform.truth.bearings_rad)[0] == 0
    assert angle_error(est, tx) < math.radians(1.0)
    # the fused objective at the sampled pan, over the second turn, is largest near the Tx
    rewards = np.array([d.reward for d in decisions[72:]])
    assert angle_error(pans[72 + int(np.argmax(rewards))], tx) <= sc.fov_half_angle_rad
    far = np.abs(physics.wrap(pans[72:] - tx)) > math.radians(60.0)
    assert rewards.max() > 2.0 * rewards[far].max()


@pytest.mark.parametrize("tx_deg", [30.0, -100.0, 179.0])
def test_paper_reward_prefers_misalignment_ours_does_not(tx_deg, paper_pod):
    """The paper's y = y_D y_RF with y_D = -|p_hat - p~| <= 0 and
    y_RF = |z_dir| >= 0 is never positive, so on the same measurements it is maximised where
    Rx(dir) hears nothing, far from the Tx; the controller's fused objective peaks at the Tx."""
    sc = small_scenario(steps=144, n_targets=6)
    platform = make_platform(sc, _layout(tx_deg), tx_index=0, seed=1)
    pans = sweep_pans(72, rounds=2)
    ms = [platform.sense(t, p) for t, p in enumerate(pans)]
    c = new_controller("ra2vipas", sc, paper_pod.model)
    ours = np.array([c.step(m).reward for m in ms])
    p_hat = float(predict(paper_pod.model, np.mean([m.rf.iso_rssi_dbm for m in ms])))
    p_tilde = np.array([np.mean([bool(f.box_bearings_rad) for f in m.frames]) for m in ms])
    y_paper = -np.abs(p_hat - p_tilde) * np.abs([m.rf.dir_rssi_dbm for m in ms])
    tx = platform.truth.tx_bearing_rad
    assert np.all(y_paper <= 0.0)
    assert angle_error(pans[int(np.argmax(y_paper))], tx) > math.radians(60.0)
    assert angle_error(pans[72 + int(np.argmax(ours[72:]))], tx) <= sc.fov_half_angle_rad


@pytest.fixture(scope="module")
def noisy_pod():
    """The POD model a rig with 8 dB of RSSI noise learns (its controller then knows its noise)."""
    return train_pod(small_scenario(n_train=900, rf_noise_db=8.0), seed=1)


@pytest.mark.parametrize("algorithm", ["ravipas", "ra2vipas"])
@pytest.mark.parametrize("tx_range, other_range", [(3.0, 5.0), (5.0, 3.0), (2.5, 1.0), (1.0, 2.5)])
@pytest.mark.parametrize("tx_deg, other_deg", [(30.0, 33.0), (33.0, 30.0)])
def test_the_target_whose_pod_matches_is_chosen(algorithm, tx_range, other_range, tx_deg, other_deg, noisy_pod):
    """Two targets 3 degrees apart, one is the Tx: whichever it is, and whichever side it is on,
    the controller picks the one whose detection rate matches the POD predicted from the iso
    RSSI. A score that rewarded mismatch (the paper's sign) or ignored it would not. The RSSI
    noise is raised to 8 dB so that Rx(dir) alone cannot tell 3 degrees apart."""
    paper_pod = noisy_pod
    sc = small_scenario(steps=144, n_targets=3, rf_noise_db=8.0)
    assert abs(physics.pod(sc, tx_range) - physics.pod(sc, other_range)) > 0.3
    layout = polar_positions([tx_range, other_range, 6.0], [tx_deg, other_deg, -120.0])
    platform = make_platform(sc, layout, tx_index=0, seed=2)
    decisions = run_open_loop(new_controller(algorithm, sc, paper_pod.model), platform, sweep_pans(72, rounds=2))
    chosen = associate(np.array([d.estimate_rad for d in decisions[-20:]]), platform.truth.bearings_rad)
    assert np.all(chosen == 0)


# -- 2. wrap-around -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["paper", "db-gain"])
@pytest.mark.parametrize("tx_deg", [179.0, -179.5, 180.0])
def test_tx_behind_the_platform_is_found_in_closed_loop(model, tx_deg, paper_pod):
    sc = small_scenario(antenna_model=model, n_targets=6)
    platform = make_platform(sc, _layout(tx_deg), tx_index=0, seed=3)
    decisions = run_closed_loop(new_controller("ra2vipas", sc, paper_pod.model), platform, sc.steps)
    est = decisions[-1].estimate_rad
    assert associate(np.array([est]), platform.truth.bearings_rad)[0] == 0
    assert angle_error(est, platform.truth.tx_bearing_rad) < math.radians(1.0)


# -- closed loop on random worlds ---------------------------------------------------------------------------


@pytest.mark.parametrize("model", ["paper", "db-gain"])
def test_ra2vipas_discovers_the_tx_on_random_worlds(model, small_pod):
    sc = small_scenario(steps=60, antenna_model=model)
    final = {}
    for alg in ("ra2vipas", "rapas", "ravipas"):
        outcomes = [run_test(sc, 2024, k, alg, small_pod.model) for k in range(12)]
        final[alg] = np.mean([o.hits[-1] for o in outcomes])
        if alg == "ra2vipas":
            at_4s = np.mean([o.hits[39] for o in outcomes])
    assert final["ra2vipas"] >= 11 / 12
    assert at_4s >= 10 / 12
    assert final["ra2vipas"] >= final["rapas"]
    assert final["ra2vipas"] >= final["ravipas"]


# -- occlusion: a Tx the camera never sees, right behind a target it sees ------------------------------------


@pytest.mark.parametrize("offset_deg", [-3.0, 3.0])
def test_a_tx_hidden_behind_a_nearer_target_is_named_where_rx_dir_puts_it(offset_deg, paper_pod):
    """The Tx stands 4 m away, 3 degrees from a person 1.5 m away whose body hides it in every
    frame (body_width_m 0.5). The camera never detects it, so naming the track in front (the
    nearest detection to the lobe) is wrong; the undetected-Tx hypothesis must not be crushed by
    the frames that "looked" there, since something stands in the way. With that allowance off
    (occluded_probability 0) and the generic lobe of an unknown antenna instead of the rig's
    response (whose sharper RF evidence alone outweighs those frames here), the controller names
    the person in front: the test can fail."""
    sc = small_scenario(steps=80, n_targets=4, body_width_m=0.5)
    layout = polar_positions([4.0, 1.5, 3.0, 3.0], [40.0, 40.0 + offset_deg, -60.0, 150.0])
    ranges, bearings = np.hypot(*layout.T), np.arctan2(layout[:, 1], layout[:, 0])
    assert physics.occluded(sc.body_width_m, bearings, ranges)[0] and not physics.occluded(sc.body_width_m, bearings, ranges)[1]
    answers = {}
    for occluded in (0.9, 0.0):
        platform = make_platform(sc, layout, tx_index=0, seed=4)
        settings = ControllerSettings(occluded_probability=occluded, rf_filter=occluded > 0)
        decisions = run_closed_loop(new_controller("ra2vipas", sc, paper_pod.model, settings), platform, sc.steps)
        answers[occluded] = associate(np.array([d.estimate_rad for d in decisions[-10:]]), platform.truth.bearings_rad)
    assert np.all(answers[0.9] == 0), answers
    assert np.all(answers[0.0] == 1), answers


def test_a_tx_that_walks_across_plus_minus_pi_is_found(paper_pod):
    """The Tx walks at 3 m from bearing 160 to 200 degrees, through +-pi, while four people
    stand elsewhere (one of them 15 degrees from its start): at the end Ra²ViPAS names it,
    where it is then, not where it started."""
    from ra2vipas.services.sensors.world import GroundTruth, SimulatedPlatform

    sc = small_scenario(steps=120, n_targets=5)
    steps = sc.steps
    angles = np.radians(np.linspace(160.0, 200.0, steps))
    tx_path = np.column_stack([3.0 * np.cos(angles), 3.0 * np.sin(angles)])[:, None, :]
    standing = polar_positions([3.5, 2.5, 4.0, 3.0], [145.0, -60.0, 30.0, 100.0])
    layout = GroundTruth(positions_m=np.vstack([tx_path[0], standing]), tx_index=0,
                         walkers=np.array([0]), walker_positions_m=tx_path)
    platform = SimulatedPlatform(sc, 5, 0, layout=layout)
    decisions = run_closed_loop(new_controller("ra2vipas", sc, paper_pod.model), platform, steps)
    final_bearings = platform.truth.step_bearings_rad()[-1]
    assert associate(np.array([decisions[-1].estimate_rad]), final_bearings)[0] == 0
    assert angle_error(decisions[-1].estimate_rad, final_bearings[0]) < math.radians(5.0)
