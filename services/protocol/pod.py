"""The learned POD model as it travels from the learner to the controllers.

A compact artifact: the posterior mean and standard deviation of p_D on a grid of iso RSSI
values (paper eq. 19, p_D as a function of r). Controllers interpolate it and never refit.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator


class PODModel(BaseModel):
    """p_hat_D(r) on a grid of iso RSSI values, with its uncertainty."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    rssi_grid_dbm: tuple[float, ...] = Field(min_length=2, max_length=4096, description="increasing iso RSSI values r [dBm]")
    mean: tuple[float, ...] = Field(min_length=2, max_length=4096, description="posterior mean of p_D(r), clipped to [0, 1]")
    std: tuple[float, ...] = Field(min_length=2, max_length=4096, description="posterior standard deviation of p_D(r)")
    rf_noise_db: float = Field(ge=0.0, description="RSSI noise the learner estimated from the training stream [dB]")
    rf_noise_correlation: float = Field(0.0, ge=0.0, lt=1.0, description=(
        "lag-1 correlation of that noise from one RF sample to the next (AR(1) fading; 0: white, and what a v1 learner means)"),
        json_schema_extra={"since": "1.1"})
    n_train: int = Field(ge=1, description="training samples the model was fitted on")
    frames_per_rf: int = Field(ge=1, description="nu the labels were computed with")

    @model_validator(mode="after")
    def _same_length(self) -> "PODModel":
        n = len(self.rssi_grid_dbm)
        if len(self.mean) != n or len(self.std) != n:
            raise ValueError("rssi_grid_dbm, mean and std must have the same length")
        if any(b <= a for a, b in zip(self.rssi_grid_dbm, self.rssi_grid_dbm[1:])):
            raise ValueError("rssi_grid_dbm must be strictly increasing")
        return self
