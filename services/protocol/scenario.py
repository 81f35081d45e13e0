"""The scenario: every parameter of the paper's Table I (and of the authors' code), plus the
cluttered, dynamic world beyond it (walkers, occlusion, clutter, shadowing, fading; all off in
the paper presets), as one validated object, with the named presets users start from.

A scenario travels on the wire (the orchestrator sends it with each episode), so it lives in
the protocol package and depends only on pydantic. Field names follow the paper's symbols;
each field's description names the symbol and its ``ge``/``le`` bounds are the allowed range
that error messages quote.
"""

from __future__ import annotations

import difflib
import math
from enum import Enum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

MAX_TRUTH_WALKER_STEPS = 40_000
"""The most walker-steps (walkers x steps) a scenario may have: each one is a bearing and a
range in the episode's ground truth message, which must stay well under the 1 MiB payload
limit (docs/protocol.md)."""


class Placement(str, Enum):
    """How targets are drawn around the platform.

    ``reference`` follows the authors' public code: targets uniform in the square
    [-w, w]^2, the Tx within ``tx_max_range_m`` of the platform and every other target's
    range differing from the Tx's by more than ``min_range_gap_m``. ``uniform`` drops the
    two range constraints.
    """

    reference = "reference"
    uniform = "uniform"


class AntennaModel(str, Enum):
    """How Rx(dir) responds to the misalignment Delta = wrap(s - gamma).

    ``paper``: z_dir = g(d) * rho(s, gamma) (paper eq. 6), a dBm value scaled by the
    attenuation factor, so |z_dir| grows with alignment. ``db-gain``: the physically sound
    model z_dir = g(d) + 10 log10(max(rho, floor)), an antenna gain in dB added to the
    path loss, so z_dir is highest when aligned.
    """

    paper = "paper"
    db_gain = "db-gain"


class RadioMode(str, Enum):
    """What the receivers deliver each control step (protocol 1.3; docs/radio.md).

    ``pair``: the paper's radio, one real-valued (iso, dir) RSSI pair every T_RF (eq. 8).
    ``adverts``: BLE advertisements: the beacon advertises every ``adv_interval_s`` plus BLE's
    random advDelay, each receiver hears some of them (loss, sensitivity, the scan channel),
    each packet with its own RSSI (per-channel offset, per-packet spread, quantised); a step
    carries 0..n of them per receiver. ``recorded``: the same packets, but which arrive, when
    and at what RSSI are drawn from a recorded channel file (``radio_channel``).
    """

    pair = "pair"
    adverts = "adverts"
    recorded = "recorded"


SINCE_1_3 = {"since": "1.3"}
"""Schema mark of a scenario parameter added in protocol 1.3: omitted on the wire at its default."""
SINCE_1_4 = {"since": "1.4"}
"""Schema mark of a scenario parameter added in protocol 1.4 (many tags, issue 21; docs/tags.md)."""
MAX_TAGS = 64
CHANNEL_NAME_PATTERN = r"^[a-z0-9][a-z0-9_.-]{0,63}$"


class Scenario(BaseModel):
    """One simulated world and its sensors (paper, Table I).

    Angles are given in degrees on the wire and in the CLI (``*_deg``); the code converts to
    radians where it computes.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", use_enum_values=False)

    # -- timing (paper eqs. 1-4) ---------------------------------------------------------
    rf_period_s: float = Field(0.1, gt=0.0, le=10.0, description="T_RF, RF sampling period; one control decision per RF sample [s]")
    frames_per_rf: int = Field(10, ge=1, le=1000, description="nu, camera frames per RF sample (eq. 4)")
    steps: int = Field(120, ge=1, le=10000, description="n_test, RF samples (control steps) per test")
    n_train: int = Field(900, ge=20, le=100000, description="n_train, POD training samples (eq. 20)")
    # -- targets --------------------------------------------------------------------------
    n_targets: int = Field(20, ge=1, le=500, description="N, number of targets around the platform")
    placement: Placement = Field(Placement.reference, description="target placement rule: reference|uniform")
    arena_half_width_m: float = Field(5.0, gt=0.0, le=1000.0, description="targets are drawn uniformly in [-w, w]^2 [m]")
    min_target_range_m: float = Field(0.5, ge=0.0, le=100.0, description="no target closer to the platform than this [m]")
    tx_max_range_m: float = Field(4.0, gt=0.0, le=1000.0, description="reference placement: the Tx lies within this range [m]")
    min_range_gap_m: float = Field(1.0, ge=0.0, le=100.0, description="reference placement: |d_i - d_Tx| exceeds this for every other target [m]")
    # -- training motion (Table I) --------------------------------------------------------
    train_step_var_m2: float = Field(0.04, ge=0.0, le=4.0, description="variance of eta_t in d_{t+1} = d_t + eta_t [m^2]")
    train_min_range_m: float = Field(0.5, gt=0.0, le=100.0, description="training motion is kept above this range [m]")
    train_max_range_m: float = Field(7.0, gt=0.0, le=1000.0, description="training motion is kept below this range [m]")
    # -- radio (eqs. 5-8) -----------------------------------------------------------------
    path_loss_ref_dbm: float = Field(-30.0, ge=-150.0, le=30.0, description="kappa, RSSI at the reference distance [dBm]")
    path_loss_exponent: float = Field(2.0, ge=0.5, le=10.0, description="n, path-loss exponent")
    path_loss_ref_distance_m: float = Field(1.0, gt=0.0, le=100.0, description="delta, reference distance [m]")
    antenna_model: AntennaModel = Field(AntennaModel.paper, description="Rx(dir) response: paper|db-gain")
    antenna_curvature: float = Field(0.5, ge=0.0, le=100.0, description="a in rho = 1 - a * Delta^2, clipped to [0, 1]")
    antenna_floor_db: float = Field(-20.0, ge=-100.0, le=0.0, description="db-gain model: lowest gain of Rx(dir) [dB]")
    rf_noise_db: float = Field(3.0, ge=0.0, le=30.0, description="sigma_RF, Gaussian RSSI noise on both receivers [dB]")
    # -- camera (eq. 9, eq. 22) -----------------------------------------------------------
    fov_half_angle_deg: float = Field(22.5, gt=0.0, le=180.0, description="camera half field of view [deg]")
    pod_far_slope: float = Field(4.0, ge=0.0, le=100.0, description="slope of the far logistic in p_D(d) (4 in eq. 22) [1/m]")
    pod_far_range_m: float = Field(4.5, ge=0.0, le=100.0, description="midpoint of the far logistic in p_D(d) (4.5 in eq. 22) [m]")
    pod_near_slope: float = Field(1.0, ge=0.0, le=100.0, description="slope of the near logistic in p_D(d) (1 in eq. 22) [1/m]")
    pod_near_range_m: float = Field(2.5, ge=0.0, le=100.0, description="midpoint of the near logistic in p_D(d) (2.5 in eq. 22) [m]")
    box_bearing_noise_deg: float = Field(0.25, ge=0.0, le=10.0, description="std of the bearing of a detector box (not in the paper) [deg]")
    initial_pan_deg: float = Field(0.0, ge=-180.0, le=180.0, description="pan angle s_0 at the start of each test [deg]")
    # -- a cluttered, dynamic world (not in the paper; every effect off by default) --------
    walking_fraction: float = Field(0.0, ge=0.0, le=1.0, description="share of the N targets that walk, drawn at random per test, the Tx included in the draw (0 = all static)")
    walk_speed_mps: float = Field(1.0, ge=0.0, le=10.0, description="v, walking speed; each walker's speed is uniform in [0.5, 1] x v [m/s]")
    walk_turn_deg_per_s: float = Field(30.0, ge=0.0, le=720.0, description="sigma_theta, std of the walkers' Brownian heading: it changes by N(0, sigma_theta^2 T_RF) every T_RF [deg/sqrt(s)]")
    body_width_m: float = Field(0.0, ge=0.0, le=5.0, description="w_b, every target is a disc of this width; a target more than half hidden behind a nearer one is not detected (0 = no occlusion) [m]")
    clutter_rate: float = Field(0.0, ge=0.0, le=100.0, description="lambda_c, false boxes per frame, Poisson, uniform over the field of view [1/frame]")
    shadowing_db: float = Field(0.0, ge=0.0, le=30.0, description="sigma_S, std of the log-normal shadowing of the Tx's signal, common to both receivers (0 = none) [dB]")
    shadowing_corr_m: float = Field(2.0, gt=0.0, le=1000.0, description="d_corr, shadowing decorrelation distance: correlation exp(-Delta/d_corr) between Tx positions Delta apart (Gudmundson) [m]")
    fading_corr_s: float = Field(0.0, ge=0.0, le=1000.0, description="tau, correlation time of the RSSI noise: AR(1) with lag-1 correlation exp(-T_RF/tau) on each receiver (0 = white) [s]")
    # -- real radios: BLE advertisements (protocol 1.3, issue 20; docs/radio.md; used when radio != pair) --
    radio: RadioMode = Field(RadioMode.pair, json_schema_extra=SINCE_1_3, description="what the receivers deliver per step: pair (the paper's one RSSI pair per T_RF)|adverts (simulated BLE advertisements, 0..n per step)|recorded (advertisements drawn from a recorded channel)")
    adv_interval_s: float = Field(0.45, ge=0.02, le=10.24, json_schema_extra=SINCE_1_3, description="T_adv, the beacon's advertising interval, before advDelay (BLE: 20 ms to 10.24 s) [s]")
    adv_delay_max_s: float = Field(0.01, ge=0.0, le=0.1, json_schema_extra=SINCE_1_3, description="advDelay, uniform in [0, this] added to every advertising interval (BLE: 0-10 ms) [s]")
    scan_interval_s: float = Field(1.2, gt=0.0, le=100.0, json_schema_extra=SINCE_1_3, description="each receiver listens on one advertising channel (37, 38, 39 in turn) for this long, from a random phase [s]")
    packet_loss_iso: float = Field(0.1, ge=0.0, lt=1.0, json_schema_extra=SINCE_1_3, description="probability that Rx(iso) misses an advertisement sent on the channel it listens to")
    packet_loss_dir: float = Field(0.1, ge=0.0, lt=1.0, json_schema_extra=SINCE_1_3, description="probability that Rx(dir) misses an advertisement sent on the channel it listens to")
    rx_sensitivity_dbm: float = Field(-65.0, ge=-200.0, le=50.0, json_schema_extra=SINCE_1_3, description="receiver sensitivity: a packet whose RSSI would be below this is lost [dBm]")
    rssi_step_db: float = Field(1.0, ge=0.0, le=10.0, json_schema_extra=SINCE_1_3, description="RSSI quantisation step: reported RSSI = step * round(RSSI / step) (1: whole dBm; 0: none) [dB]")
    channel_offset_db: float = Field(3.0, ge=0.0, le=30.0, json_schema_extra=SINCE_1_3, description="sigma_ch, std of the per-receiver, per-advertising-channel RSSI offsets (frequency-selective fading), drawn once per test [dB]; rf_noise_db is then the per-packet spread")
    radio_channel: str = Field("cc0-tetam", pattern=CHANNEL_NAME_PATTERN, json_schema_extra=SINCE_1_3, description="radio recorded: the recorded channel file, by name (a shipped one, or one in $RA2VIPAS_CHANNELS; ra2vipas radio import)")
    # -- boxes with a size (protocol 1.3) ---------------------------------------------------
    box_heights: bool = Field(False, json_schema_extra=SINCE_1_3, description="every box carries its angular height: from the target's height and range (clutter: a plausible person's), with noise")
    target_height_min_m: float = Field(1.5, gt=0.0, le=10.0, json_schema_extra=SINCE_1_3, description="each target's height is uniform in [min, max] (people: 1.5-1.9 m) [m]")
    target_height_max_m: float = Field(1.9, gt=0.0, le=10.0, json_schema_extra=SINCE_1_3, description="upper end of the targets' heights [m]")
    camera_height_m: float = Field(1.0, ge=0.0, le=10.0, json_schema_extra=SINCE_1_3, description="height of the camera's axis above the floor: a box spans atan((H - h_c)/d) + atan(h_c/d) [m]")
    box_height_noise: float = Field(0.05, ge=0.0, le=1.0, json_schema_extra=SINCE_1_3, description="relative std of a box's angular height (multiplicative Gaussian noise)")
    # -- many tags (protocol 1.4, issue 21; docs/tags.md) -------------------------------------
    n_tags: int = Field(1, ge=1, le=MAX_TAGS, json_schema_extra=SINCE_1_4, description="K, transmitters (tags) in the scene, each with its own address and advertising schedule; tag 0 is the paper's Tx")
    one_tag_per_person: bool = Field(True, json_schema_extra=SINCE_1_4, description="true: the K tags are carried by K distinct targets; false: each tag's carrier is drawn on its own (two tags may share a person)")

    @model_validator(mode="before")
    @classmethod
    def _strict_numbers(cls, data: Any) -> Any:
        """Numbers must be numbers: a string or a boolean is never coerced into an integer or a
        number (the same rule for the CLI, the API and the wire), an integer parameter takes no
        fraction, and -0.0 is 0.0 (so a parameter that must be positive refuses it, and one
        that may be zero accepts it as zero)."""
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for name, value in data.items():
            info = cls.model_fields.get(name)
            if info is None or info.annotation not in (int, float):
                continue
            wrong = isinstance(value, bool) or not isinstance(value, (int, float))
            if not wrong and info.annotation is int and isinstance(value, float):
                wrong = not value.is_integer()
                if not wrong:
                    out[name] = int(value)
            if wrong:
                raise ValueError(f"{name}: expected {field_range(name)}, got {value!r}")
            if isinstance(value, float) and value == 0.0:
                out[name] = 0.0  # -0.0 -> 0.0
        return out

    @model_validator(mode="after")
    def _consistent(self) -> "Scenario":
        if self.train_min_range_m >= self.train_max_range_m:
            raise ValueError(
                f"train_min_range_m ({self.train_min_range_m}) must be below train_max_range_m ({self.train_max_range_m})"
            )
        corner = self.arena_half_width_m * math.sqrt(2.0)
        if self.min_target_range_m >= corner:
            raise ValueError(
                f"min_target_range_m ({self.min_target_range_m}) must be below the arena's corner range {corner:.3g} m"
            )
        if self.placement is Placement.reference and self.tx_max_range_m <= self.min_target_range_m:
            raise ValueError(
                f"tx_max_range_m ({self.tx_max_range_m}) must exceed min_target_range_m ({self.min_target_range_m})"
            )
        if self.target_height_min_m > self.target_height_max_m:
            raise ValueError(f"target_height_min_m ({self.target_height_min_m}) must not exceed target_height_max_m ({self.target_height_max_m})")
        if self.one_tag_per_person and self.n_tags > self.n_targets:
            raise ValueError(f"n_tags ({self.n_tags}) exceeds n_targets ({self.n_targets}) while one_tag_per_person is true; "
                             "lower n_tags or set one_tag_per_person=false")
        walker_steps = self.n_walkers * self.steps
        if walker_steps > MAX_TRUTH_WALKER_STEPS:
            raise ValueError(
                f"walking_fraction ({self.walking_fraction}) x n_targets ({self.n_targets}) gives {self.n_walkers} walkers"
                f" x {self.steps} steps = {walker_steps} walker-steps of ground truth, more than the {MAX_TRUTH_WALKER_STEPS}"
                " an episode's truth message can carry; lower steps, n_targets or walking_fraction"
            )
        return self

    # -- derived quantities ------------------------------------------------------------------
    @property
    def n_walkers(self) -> int:
        """How many targets walk in each test: walking_fraction * N rounded half up."""
        return int(math.floor(self.walking_fraction * self.n_targets + 0.5))

    # -- derived quantities in radians ------------------------------------------------------
    @property
    def walk_turn_rad_per_sqrt_s(self) -> float:
        return math.radians(self.walk_turn_deg_per_s)

    @property
    def fov_half_angle_rad(self) -> float:
        return math.radians(self.fov_half_angle_deg)

    @property
    def box_bearing_noise_rad(self) -> float:
        return math.radians(self.box_bearing_noise_deg)

    @property
    def initial_pan_rad(self) -> float:
        return math.radians(self.initial_pan_deg)

    @property
    def duration_s(self) -> float:
        """T_W = n_test * T_RF, the duration of one test."""
        return self.steps * self.rf_period_s


PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "paper-uniform": {"placement": "uniform"},
    "dynamic": {
        "walking_fraction": 0.5,
        "walk_speed_mps": 1.0,
        "walk_turn_deg_per_s": 30.0,
        "body_width_m": 0.5,
        "clutter_rate": 0.3,
        "shadowing_db": 4.0,
        "shadowing_corr_m": 2.0,
        "fading_corr_s": 0.5,
        "box_bearing_noise_deg": 1.0,
    },
}
_BLE_RADIO: dict[str, Any] = {
    # docs/radio.md: every value and where it comes from (the CC0 BLE dataset, Danis et al. 2022)
    "radio": "adverts",
    "antenna_model": "db-gain",
    "rf_noise_db": 1.6,
    "channel_offset_db": 3.0,
    "shadowing_db": 3.8,
    "shadowing_corr_m": 1.5,
}
PRESETS["ble"] = dict(_BLE_RADIO)
PRESETS["ble-dynamic"] = {**PRESETS["dynamic"], **_BLE_RADIO}
PRESETS["ble-recorded"] = {
    # the shipped channel's pooled log-distance fit (its meta, ra2vipas radio import): what a model of it assumes
    "radio": "recorded", "antenna_model": "db-gain", "radio_channel": "cc0-tetam", "path_loss_ref_dbm": -61.66,
    "path_loss_exponent": 1.413, "rf_noise_db": 3.0,
}
PRESETS["ward"] = {**PRESETS["dynamic"], "n_tags": 3}
"""Named starting points: overrides applied on top of the field defaults (the paper's values)."""

PRESET_DESCRIPTIONS: dict[str, str] = {
    "paper": "Table I of the paper with the authors' reference placement (Tx within 4 m, others' range differs by > 1 m)",
    "paper-uniform": "Table I of the paper with targets uniform in the square, no range constraint",
    "dynamic": "a cluttered, dynamic world: paper placement at t=0, half the targets walk (1 m/s), 0.5 m bodies occlude,"
               " 0.3 false boxes per frame, 4 dB shadowing (2 m), RSSI noise correlated over 0.5 s, 1 deg box noise",
    "ble": "the paper's targets heard by BLE receivers with the statistics of a real building (CC0 dataset, docs/radio.md):"
           " an advertisement every 0.45-0.46 s, 10 % loss, whole-dBm RSSI, 3 dB per-channel offsets, 1.6 dB per-packet spread,"
           " 3.8 dB shadowing (1.5 m), db-gain antenna, at the paper's kappa",
    "ble-dynamic": "the dynamic world (walkers, occlusion, clutter) heard by the ble preset's radio",
    "ward": "the dynamic world with K = 3 tags, each carried by a different person (docs/tags.md)",
    "ble-recorded": "the paper's targets; each receiver's packets (which arrive, when, at what whole-dBm RSSI) drawn from"
                    " recordings of a real building (the shipped CC0 subset, docs/radio.md), with its spatial shadowing",
}


class ScenarioError(ValueError):
    """A scenario could not be built; the message is one line naming the field and the allowed values."""


def field_range(name: str) -> str:
    """Human description of what a scenario field accepts, e.g. ``an integer in [1, 500]``."""
    info = Scenario.model_fields[name]
    annotation = info.annotation
    if isinstance(annotation, type) and issubclass(annotation, Enum):
        return "one of " + "|".join(m.value for m in annotation)
    if annotation is bool:
        return "one of true|false"
    if annotation is str:
        pattern = next((getattr(m, "pattern", None) for m in info.metadata if getattr(m, "pattern", None)), None)
        return f"a name in {pattern}" if pattern else "a text"
    lo = hi = None
    lo_open = hi_open = False
    for meta in info.metadata:
        if getattr(meta, "ge", None) is not None:
            lo = meta.ge
        if getattr(meta, "gt", None) is not None:
            lo, lo_open = meta.gt, True
        if getattr(meta, "le", None) is not None:
            hi = meta.le
        if getattr(meta, "lt", None) is not None:
            hi, hi_open = meta.lt, True
    kind = "an integer" if annotation is int else "a number"
    if lo is None and hi is None:
        return kind
    left = "(" if lo_open else "["
    right = ")" if hi_open else "]"
    return f"{kind} in {left}{lo}, {hi}{right}"


def _explain(err: ValidationError, given: dict[str, Any]) -> str:
    first = err.errors()[0]
    loc = first.get("loc") or ()
    if loc and isinstance(loc[0], str) and loc[0] in Scenario.model_fields:
        name = loc[0]
        if first.get("type") == "extra_forbidden":
            return f"unknown scenario parameter {name!r}; known: {', '.join(Scenario.model_fields)}"
        return f"{name}: expected {field_range(name)}, got {given.get(name)!r}"
    if loc and isinstance(loc[0], str) and first.get("type") == "extra_forbidden":
        return f"unknown scenario parameter {loc[0]!r}; known: {', '.join(Scenario.model_fields)}"
    msg = str(first.get("msg", err))
    return msg.removeprefix("Value error, ")


def build_scenario(preset: str = "paper", overrides: dict[str, Any] | None = None) -> Scenario:
    """The scenario of ``preset`` with ``overrides`` applied.

    Raises
    ------
    ScenarioError
        Unknown preset, unknown parameter, or a value out of its range; the message names
        the field and what it accepts.
    """
    if preset not in PRESETS:
        raise ScenarioError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    values = {**PRESETS[preset], **(overrides or {})}
    for name in values:
        if name not in Scenario.model_fields:
            raise ScenarioError(f"unknown scenario parameter {name!r}{suggest_parameter(name)}; known: {', '.join(Scenario.model_fields)}")
    try:
        return Scenario.model_validate(values)
    except ValidationError as err:
        raise ScenarioError(_explain(err, values)) from None


def suggest_parameter(name: str) -> str:
    """`` (did you mean 'n_targets'?)`` for a misspelt parameter name, or ``""``."""
    close = difflib.get_close_matches(name, list(Scenario.model_fields), n=1, cutoff=0.75)
    return f" (did you mean {close[0]!r}?)" if close else ""


def parse_value(name: str, text: str) -> Any:
    """The typed value of a CLI ``NAME=VALUE``: an integer or a number for numeric parameters
    (never coerced by the scenario itself), the text for the others.

    Raises
    ------
    ScenarioError
        A numeric parameter whose text is not a number of its kind; an unknown parameter.
    """
    info = Scenario.model_fields.get(name)
    if info is None:
        raise ScenarioError(f"unknown scenario parameter {name!r}{suggest_parameter(name)}; known: {', '.join(Scenario.model_fields)}")
    text = text.strip()
    if info.annotation is bool:
        if text.lower() not in ("true", "false", "1", "0", "yes", "no", "on", "off"):
            raise ScenarioError(f"{name}: expected {field_range(name)}, got {text!r}")
        return text.lower() in ("true", "1", "yes", "on")
    try:
        if info.annotation is int:
            return int(text)
        if info.annotation is float:
            value = float(text)
            if not math.isfinite(value):
                raise ValueError
            return value
    except ValueError:
        raise ScenarioError(f"{name}: expected {field_range(name)}, got {text!r}") from None
    return text


def parse_overrides(assignments: list[str] | tuple[str, ...]) -> dict[str, Any]:
    """Turn CLI ``NAME=VALUE`` strings into typed overrides (see ``parse_value``).

    Raises
    ------
    ScenarioError
        An assignment without ``=`` or with an empty name, an unknown parameter, or a value that
        is not of the parameter's kind.
    """
    out: dict[str, Any] = {}
    for item in assignments:
        name, sep, value = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise ScenarioError(f"--set expects NAME=VALUE, got {item!r}")
        out[name] = parse_value(name, value)
    return out
