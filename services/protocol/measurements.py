"""What the sensors measure: the only inputs the controller and the learner ever receive.

These models carry measurements exactly as real hardware produces them: two RSSI values
per RF sample and, per camera frame, the bearings of the detector's boxes relative to the
optical axis. No target identity, range, POD or Tx flag exists in any of them; the
simulator's ground truth travels separately (``ra2vipas.services.sensors.world.GroundTruth``).

Angles are radians, positive counter-clockwise (the paper's frame F_0); RSSI is dBm.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class _Measurement(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)


class RFSample(_Measurement):
    """One RF sample (paper eq. 8): z_RF^(iso) and z_RF^(dir), taken together every T_RF."""

    iso_rssi_dbm: float = Field(description="z^(iso), RSSI at the omnidirectional receiver [dBm]")
    dir_rssi_dbm: float = Field(description="z^(dir), RSSI at the directional receiver [dBm]")


class CameraFrame(_Measurement):
    """The detector's output for one camera frame: one bearing per box, no identities.

    Bearings are relative to the optical axis (inside the field of view) and sorted, so the
    order of boxes says nothing about which target produced them.
    """

    box_bearings_rad: tuple[float, ...] = Field(default=(), max_length=1000, description="box bearings w.r.t. the optical axis [rad]")


class StepMeasurement(_Measurement):
    """What the platform senses at one control step t: the pan angle it was at, the RF
    sample and the nu camera frames taken before it (paper eq. 21)."""

    step: int = Field(ge=0, description="t, index of the RF sample within the test")
    pan_rad: float = Field(description="s_t, pan angle at which the sample was taken [rad]")
    rf: RFSample
    frames: tuple[CameraFrame, ...] = Field(max_length=10000)


class TrainingSample(_Measurement):
    """One sample of the self-supervised POD training episode: an iso RSSI value and the nu
    frames the camera took while the Tx walked in view (paper eqs. 20-21)."""

    index: int = Field(ge=0, description="j, index in the training episode")
    iso_rssi_dbm: float = Field(description="z^(iso)_j [dBm]")
    frames: tuple[CameraFrame, ...] = Field(max_length=10000)
