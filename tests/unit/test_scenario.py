"""Scenario: Table I as validated parameters, presets, and one-line errors naming the field."""

from __future__ import annotations

import json
import math

import pydantic
import pytest
from pydantic import ValidationError

from ra2vipas.services.protocol.scenario import (
    PRESETS,
    AntennaModel,
    Placement,
    Scenario,
    ScenarioError,
    build_scenario,
    field_range,
    parse_overrides,
)


def test_paper_preset_is_table_one():
    sc = build_scenario("paper")
    assert sc.rf_period_s == 0.1
    assert sc.frames_per_rf == 10
    assert sc.steps == 120
    assert sc.n_train == 900
    assert sc.n_targets == 20
    assert sc.train_step_var_m2 == 0.04
    assert (sc.train_min_range_m, sc.train_max_range_m) == (0.5, 7.0)
    assert (sc.path_loss_ref_dbm, sc.path_loss_exponent, sc.path_loss_ref_distance_m) == (-30.0, 2.0, 1.0)
    assert sc.antenna_curvature == 0.5
    assert sc.rf_noise_db == 3.0
    assert (sc.pod_far_slope, sc.pod_far_range_m, sc.pod_near_slope, sc.pod_near_range_m) == (4.0, 4.5, 1.0, 2.5)
    # from the authors' code
    assert sc.fov_half_angle_rad == pytest.approx(math.pi / 8)
    assert sc.arena_half_width_m == 5.0
    assert sc.tx_max_range_m == 4.0
    assert sc.min_range_gap_m == 1.0
    assert sc.initial_pan_rad == 0.0
    assert sc.placement is Placement.reference
    assert sc.antenna_model is AntennaModel.paper
    assert sc.duration_s == pytest.approx(12.0)


def test_paper_uniform_differs_only_in_placement():
    paper = build_scenario("paper").model_dump()
    uniform = build_scenario("paper-uniform").model_dump()
    assert uniform["placement"] is Placement.uniform
    diff = {k for k in paper if paper[k] != uniform[k]}
    assert diff == {"placement"}


def test_presets_all_build():
    for name in PRESETS:
        assert isinstance(build_scenario(name), Scenario)


def test_overrides_are_applied_and_coerced_from_strings():
    sc = build_scenario("paper", parse_overrides(["steps=40", "rf_noise_db=1.5", "antenna_model=db-gain", "placement=uniform"]))
    assert sc.steps == 40 and isinstance(sc.steps, int)
    assert sc.rf_noise_db == 1.5
    assert sc.antenna_model is AntennaModel.db_gain
    assert sc.placement is Placement.uniform


def test_overrides_on_top_of_preset():
    sc = build_scenario("paper-uniform", {"n_targets": 5})
    assert sc.placement is Placement.uniform and sc.n_targets == 5


def test_json_round_trip():
    sc = build_scenario("paper", {"steps": 40, "antenna_model": "db-gain", "initial_pan_deg": -90})
    again = build_scenario("paper", sc.model_dump(mode="json"))
    assert again == sc


def test_scenario_is_frozen():
    sc = build_scenario("paper")
    with pytest.raises(pydantic.ValidationError):
        sc.steps = 3


def test_scenario_error_is_a_value_error():
    assert issubclass(ScenarioError, ValueError)


@pytest.mark.parametrize(
    "name, value, allowed",
    [
        ("n_targets", 0, "[1, 500]"),
        ("n_targets", 501, "[1, 500]"),
        ("steps", 0, "[1, 10000]"),
        ("n_train", 19, "[20, 100000]"),
        ("frames_per_rf", 0, "[1, 1000]"),
        ("rf_noise_db", -1.0, "[0.0, 30.0]"),
        ("rf_period_s", 0.0, "(0.0, 10.0]"),
        ("fov_half_angle_deg", 200.0, "(0.0, 180.0]"),
        ("initial_pan_deg", 181.0, "[-180.0, 180.0]"),
    ],
)
def test_out_of_range_value_names_field_and_range(name, value, allowed):
    with pytest.raises(ScenarioError) as info:
        build_scenario("paper", {name: value})
    msg = str(info.value)
    assert name in msg
    assert allowed in msg
    assert repr(value) in msg
    assert "\n" not in msg


def test_n_targets_zero_message():
    with pytest.raises(ScenarioError) as info:
        build_scenario("paper", {"n_targets": 0})
    msg = str(info.value)
    assert "n_targets" in msg and "[1, 500]" in msg and "integer" in msg


def test_unknown_field_is_rejected():
    with pytest.raises(ScenarioError) as info:
        build_scenario("paper", {"n_tragets": 3})
    msg = str(info.value)
    assert "n_tragets" in msg and "unknown" in msg
    assert "n_targets" in msg  # lists the known parameters
    assert "\n" not in msg


@pytest.mark.parametrize("name, value", [("steps", "abc"), ("steps", 1.5), ("rf_noise_db", "loud"), ("n_targets", [3])])
def test_wrong_type_is_rejected(name, value):
    with pytest.raises(ScenarioError) as info:
        build_scenario("paper", {name: value})
    msg = str(info.value)
    assert name in msg
    assert field_range(name) in msg
    assert "\n" not in msg


def test_enum_field_lists_choices():
    with pytest.raises(ScenarioError) as info:
        build_scenario("paper", {"antenna_model": "yagi"})
    msg = str(info.value)
    assert "antenna_model" in msg and "paper" in msg and "db-gain" in msg


@pytest.mark.parametrize("lo, hi", [(7.0, 7.0), (6.0, 2.0)])
def test_training_range_must_be_ordered(lo, hi):
    with pytest.raises(ScenarioError) as info:
        build_scenario("paper", {"train_min_range_m": lo, "train_max_range_m": hi})
    msg = str(info.value)
    assert "train_min_range_m" in msg and "train_max_range_m" in msg
    assert "\n" not in msg
    assert not msg.startswith("Value error")


def test_min_target_range_beyond_arena_corner_is_rejected():
    with pytest.raises(ScenarioError, match="min_target_range_m"):
        build_scenario("paper", {"arena_half_width_m": 1.0, "min_target_range_m": 1.5})


def test_tx_range_must_exceed_min_range_only_for_reference_placement():
    with pytest.raises(ScenarioError, match="tx_max_range_m"):
        build_scenario("paper", {"tx_max_range_m": 0.4})
    assert build_scenario("paper-uniform", {"tx_max_range_m": 0.4}).tx_max_range_m == 0.4


def test_unknown_preset():
    with pytest.raises(ScenarioError) as info:
        build_scenario("papper")
    msg = str(info.value)
    assert "papper" in msg and "paper" in msg and "paper-uniform" in msg


def test_field_range_descriptions():
    assert field_range("n_targets") == "an integer in [1, 500]"
    assert field_range("rf_period_s") == "a number in (0.0, 10.0]"
    assert field_range("placement") == "one of reference|uniform"


def test_every_field_has_a_description_and_a_range():
    for name, info in Scenario.model_fields.items():
        assert info.description, name
        desc = field_range(name)
        assert desc.startswith("one of ") or " in " in desc, (name, desc)


def test_parse_overrides():
    assert parse_overrides([]) == {}
    got = parse_overrides(["steps=40", " rf_noise_db = 2 ", "placement=uniform"])
    assert got == {"steps": 40, "rf_noise_db": 2.0, "placement": "uniform"}
    assert type(got["steps"]) is int and type(got["rf_noise_db"]) is float  # typed as the scenario types them


@pytest.mark.parametrize("assignment, needle", [
    ("steps=4.5", "steps: expected an integer"), ("steps=true", "steps: expected an integer"),
    ("rf_noise_db=inf", "rf_noise_db: expected a number"), ("note=a=b", "unknown scenario parameter 'note'"),
])
def test_parse_overrides_refuses_values_of_the_wrong_kind(assignment, needle):
    with pytest.raises(ScenarioError, match=needle):
        parse_overrides([assignment])


@pytest.mark.parametrize("values", [{"n_targets": True}, {"n_targets": "30"}, {"rf_noise_db": "3"}, {"steps": 40.5},
                                    {"rf_period_s": -0.0}, {"fov_half_angle_deg": False}])
def test_numbers_are_never_coerced_from_strings_or_booleans(values):
    with pytest.raises(ScenarioError):
        build_scenario("paper", values)
    with pytest.raises(ValidationError):  # the same rule on the wire
        Scenario.model_validate_json(json.dumps(values))


def test_negative_zero_is_zero():
    sc = build_scenario("paper", {"rf_noise_db": -0.0, "train_step_var_m2": -0.0, "box_bearing_noise_deg": -0.0})
    assert math.copysign(1.0, sc.rf_noise_db) == 1.0 and math.copysign(1.0, sc.box_bearing_noise_deg) == 1.0
    assert math.copysign(1.0, sc.train_step_var_m2) == 1.0


@pytest.mark.parametrize("bad", ["steps", "=40", "  =1", ""])
def test_parse_overrides_needs_name_and_equals(bad):
    with pytest.raises(ScenarioError) as info:
        parse_overrides(["steps=1", bad])
    assert "NAME=VALUE" in str(info.value)
    assert repr(bad) in str(info.value)
