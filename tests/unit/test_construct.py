"""The cheaper model_construct (services/protocol/construct.py) builds the same objects."""

from __future__ import annotations

from ra2vipas.services.protocol.construct import builder
from ra2vipas.services.protocol.measurements import Advertisement, CameraFrame, RFSample, StepMeasurement


def _same(a, b) -> None:
    assert type(a) is type(b)
    assert list(a.__dict__.items()) == list(b.__dict__.items())
    assert a.__pydantic_fields_set__ == b.__pydantic_fields_set__
    assert a.__pydantic_extra__ == b.__pydantic_extra__ and a.__pydantic_private__ == b.__pydantic_private__
    assert repr(a) == repr(b) and a.model_dump_json() == b.model_dump_json()
    assert a.model_dump(exclude_unset=True) == b.model_dump(exclude_unset=True)


def test_the_builders_make_what_model_construct_makes():
    frame = builder(CameraFrame, "box_bearings_rad")((0.1, -0.2))
    _same(frame, CameraFrame.model_construct(box_bearings_rad=(0.1, -0.2)))
    _same(builder(CameraFrame, "box_bearings_rad", "box_heights_rad")((0.1,), (0.3,)),
          CameraFrame.model_construct(box_bearings_rad=(0.1,), box_heights_rad=(0.3,)))
    pair = builder(RFSample, "iso_rssi_dbm", "dir_rssi_dbm")(-40.0, -30.5)
    _same(pair, RFSample.model_construct(iso_rssi_dbm=-40.0, dir_rssi_dbm=-30.5))
    _same(builder(RFSample, "iso_rssi_dbm", "dir_rssi_dbm", "tag")(-40.0, -30.5, 2),
          RFSample.model_construct(iso_rssi_dbm=-40.0, dir_rssi_dbm=-30.5, tag=2))
    _same(builder(StepMeasurement, "step", "pan_rad", "rf", "frames")(3, 0.25, pair, (frame,)),
          StepMeasurement.model_construct(step=3, pan_rad=0.25, rf=pair, frames=(frame,)))
    ad = builder(Advertisement, "receiver", "rssi_dbm", "channel", "offset_s", "tag", "address")("dir", -60.0, 37, 0.01, 0, None)
    _same(ad, Advertisement.model_construct(receiver="dir", rssi_dbm=-60.0, channel=37, offset_s=0.01, tag=0, address=None))
    _same(builder(StepMeasurement, "step", "pan_rad", "rf", "frames", "adverts")(4, 0.5, None, (frame,), (ad,)),
          StepMeasurement.model_construct(step=4, pan_rad=0.5, rf=None, frames=(frame,), adverts=(ad,)))
