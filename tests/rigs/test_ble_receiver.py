"""The example node's BLE receiver driver (examples/hardware_node/ble_receiver.py) on a fake
scanner backend (no BLE adapter here): the callback stream of one tag becomes the per-step
advertisement lists, with late, lost and duplicate packets handled as documented, and every
list is a valid protocol 1.3 ``adverts``."""

from __future__ import annotations

import ast
import importlib.util
import sys

import pytest

from ra2vipas.services.protocol.messages import Measurement
from tests.integration.conftest import ROOT

HERE = ROOT / "examples" / "hardware_node"
TAG = "E7:8F:13:56:24:CE"


def _load():
    spec = importlib.util.spec_from_file_location("ble_receiver", HERE / "ble_receiver.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("ble_receiver", module)
    spec.loader.exec_module(module)
    return module


ble = _load()


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture()
def rig():
    clock = Clock()
    ble.FakeScanner.instances.clear()
    receivers = ble.BleReceivers(TAG.lower(), {"iso": "hci0", "dir": "hci1"}, scanner_factory=ble.FakeScanner, clock=clock)
    receivers.start()
    iso, dir_ = ble.FakeScanner.instances
    yield receivers, clock, iso, dir_
    receivers.stop()
    assert not iso.running and not dir_.running


def _valid(adverts):
    """The list as a Measurement's adverts: it validates against the protocol."""
    payload = {"episode_id": "e", "step": 0, "pan_rad": 0.0, "frames": []}
    if adverts:
        payload["adverts"] = adverts
    return Measurement.model_validate(payload)


def test_the_driver_imports_no_ble_library_until_a_real_scanner_starts():
    tree = ast.parse((HERE / "ble_receiver.py").read_text())
    top = {alias.name.split(".")[0] for node in tree.body if isinstance(node, ast.Import) for alias in node.names}
    top |= {node.module.split(".")[0] for node in tree.body if isinstance(node, ast.ImportFrom) and node.module}
    assert top - sys.stdlib_module_names - {"__future__"} == set()  # bleak only inside bleak_scanner()
    assert "from bleak import BleakScanner" in (HERE / "ble_receiver.py").read_text()


def test_each_step_gets_what_was_heard_since_the_previous_one(rig):
    receivers, clock, iso, dir_ = rig
    receivers.reset()  # the episode starts at t = 100.0
    clock.now = 100.03
    iso.emit(TAG, -61)
    clock.now = 100.07
    dir_.emit(TAG, -70)
    iso.emit("aa:bb:cc:dd:ee:ff", -40)  # another device: ignored
    clock.now = 100.1
    step0 = receivers.read_adverts()
    assert step0 == [{"receiver": "iso", "rssi_dbm": -61, "offset_s": 0.03}, {"receiver": "dir", "rssi_dbm": -70, "offset_s": 0.07}]
    clock.now = 100.2
    assert receivers.read_adverts() == []  # lost: nothing heard, nothing made up
    clock.now = 100.25
    iso.emit(TAG.lower(), -63)
    clock.now = 100.3
    step2 = receivers.read_adverts()
    assert step2 == [{"receiver": "iso", "rssi_dbm": -63, "offset_s": 0.05}]
    m0, m1, m2 = _valid(step0), _valid([]), _valid(step2)
    assert m0.rssi_dbm("iso") == (-61,) and m0.rssi_dbm("dir") == (-70,)
    assert m1.advertisements() == () and m1.rf is None
    assert m2.advertisements("dir") == ()


def test_duplicates_are_dropped_and_late_packets_carried_by_the_next_step(rig):
    receivers, clock, iso, dir_ = rig
    receivers.reset()
    clock.now = 100.05
    iso.emit(TAG, -60)
    clock.now = 100.052  # the same advertising event reported again within 5 ms
    iso.emit(TAG, -60)
    dir_.emit(TAG, -66)  # the other receiver's copy of the event is not a duplicate
    clock.now = 100.1
    first = receivers.read_adverts()
    assert [(a["receiver"], a["rssi_dbm"]) for a in first] == [("iso", -60), ("dir", -66)]
    assert receivers.collector.duplicates == 1
    # late: a callback the event loop ran after the step was cut, stamped before the cut
    receivers.collector.add("iso", -64, at=100.095)
    clock.now = 100.2
    late = receivers.read_adverts()
    assert late == [{"receiver": "iso", "rssi_dbm": -64, "offset_s": 0.0}]
    assert receivers.collector.late == 1
    _valid(late)


def test_a_packet_of_the_next_step_waits_for_it_and_a_new_episode_forgets_the_old_one(rig):
    receivers, clock, iso, _ = rig
    receivers.reset()
    receivers.collector.add("iso", -62, at=100.15)  # stamped after the coming cut
    clock.now = 100.1
    assert receivers.read_adverts() == []
    clock.now = 100.2
    assert receivers.read_adverts() == [{"receiver": "iso", "rssi_dbm": -62, "offset_s": 0.05}]
    iso.emit(TAG, -50)
    clock.now = 101.0
    receivers.reset()  # EpisodeStart
    clock.now = 101.1
    assert receivers.read_adverts() == []


def test_the_driver_wraps_a_node_driver_so_the_node_sends_adverts(rig):
    receivers, clock, iso, _ = rig
    node_spec = importlib.util.spec_from_file_location("hardware_node_for_ble", HERE / "hardware_node.py")
    node_module = importlib.util.module_from_spec(node_spec)
    node_spec.loader.exec_module(node_module)
    driver = ble.with_ble(node_module.FakeDriver(0), receivers)
    assert hasattr(driver, "read_adverts") and not hasattr(driver, "read_rssi")
    assert driver.move_to(0.5) == pytest.approx(0.5)  # the pan unit and the camera are the wrapped driver's
    driver.reset_adverts()
    clock.now = 100.04
    iso.emit(TAG, -58)
    clock.now = 100.1
    assert driver.read_adverts() == [{"receiver": "iso", "rssi_dbm": -58, "offset_s": 0.04}]
