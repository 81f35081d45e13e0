"""The example node's BLE receiver driver (examples/hardware_node/ble_receiver.py) on a fake
scanner backend (no BLE adapter here): the callback stream of one tag becomes the per-step
advertisement lists, with late, lost and duplicate packets handled as documented, and every
list is a valid protocol 1.3 ``adverts``; several tags' streams become protocol 1.4 lists in which
each advertisement names its tag and address; a beacon whose address changes is followed by the
identity it advertises (iBeacon, Eddystone-UID); bad addresses and scanners that cannot start are
refused in one line."""

from __future__ import annotations

import ast
import importlib.util
import sys

import pytest

from ra2vipas.services.protocol.messages import Measurement
from tests.integration.conftest import ROOT

HERE = ROOT / "examples" / "hardware_node"
TAG = "E7:8F:13:56:24:CE"
TAG2 = "C3:5A:01:9E:44:B2"
UUID = "f7826da6-4fa2-4e98-8024-bc5b71e0893e"


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


@pytest.mark.parametrize("bleak3", [False, True], ids=["bleak-0.22-2.x", "bleak-3"])
def test_a_real_scanner_asks_bluez_for_every_advertisement_on_its_adapter(monkeypatch, bleak3):
    """bleak leaves BlueZ's DuplicateData filter false (a beacon whose payload does not change is reported
    about once); the driver's scanner sets it true, and names its adapter as the installed bleak takes it
    (bleak 3: in its BlueZ arguments; before: the ``adapter`` keyword). A fake ``bleak`` module records it."""
    import types

    made = []
    fake = types.ModuleType("bleak")
    fake.BleakScanner = lambda **kwargs: made.append(kwargs) or object()
    monkeypatch.setitem(sys.modules, "bleak", fake)
    if bleak3:
        args = types.ModuleType("bleak.args")
        bluez = types.ModuleType("bleak.args.bluez")
        bluez.BlueZScannerArgs = type("BlueZScannerArgs", (), {"__annotations__": {"adapter": str, "filters": dict}})
        monkeypatch.setitem(sys.modules, "bleak.args", args)
        monkeypatch.setitem(sys.modules, "bleak.args.bluez", bluez)
    else:
        monkeypatch.setitem(sys.modules, "bleak.args", None)  # no such package before bleak 1.0
    callback = object()
    ble.bleak_scanner(callback, "hci1")
    (kwargs,) = made
    assert kwargs["detection_callback"] is callback and kwargs["bluez"]["filters"] == {"DuplicateData": True}
    if bleak3:
        assert kwargs["bluez"]["adapter"] == "hci1" and "adapter" not in kwargs
    else:
        assert kwargs["adapter"] == "hci1" and "adapter" not in kwargs["bluez"]


def test_each_step_gets_what_was_heard_since_the_previous_one(rig):
    receivers, clock, iso, dir_ = rig
    receivers.reset()  # the episode starts at t = 100.0
    clock.now = 100.03
    iso.emit(TAG, -61)
    clock.now = 100.07
    dir_.emit(TAG, -70)
    iso.emit("aa:bb:cc:dd:ee:ff", -40)  # another device: ignored
    clock.now = 100.09
    dir_.emit(TAG, -127)  # bleak's "no RSSI" (BlueZ had none for the device): not a -127 dBm packet
    clock.now = 100.1
    step0 = receivers.read_adverts()
    assert step0 == [{"receiver": "iso", "rssi_dbm": -61, "offset_s": 0.03}, {"receiver": "dir", "rssi_dbm": -70, "offset_s": 0.07}]
    assert receivers.collector.unavailable == 1
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


@pytest.fixture()
def two_tags():
    clock = Clock()
    ble.FakeScanner.instances.clear()
    receivers = ble.BleReceivers([TAG, TAG2.lower()], {"iso": "hci0", "dir": "hci1"}, scanner_factory=ble.FakeScanner, clock=clock)
    receivers.start()
    iso, dir_ = ble.FakeScanner.instances
    yield receivers, clock, iso, dir_
    receivers.stop()


def test_with_several_tags_each_advertisement_names_its_tag_and_address(two_tags):
    receivers, clock, iso, dir_ = two_tags
    assert receivers.tags == [TAG, TAG2]  # tag k is the k-th address given, upper case as the protocol writes it
    receivers.reset()
    clock.now = 100.02
    iso.emit(TAG2, -70)
    clock.now = 100.021
    iso.emit(TAG.lower(), -60)  # 1 ms after the other tag's packet on the same receiver: another packet, not a duplicate
    clock.now = 100.022
    iso.emit(TAG, -61)  # the same tag's advertising event reported again within 5 ms: a duplicate
    clock.now = 100.05
    dir_.emit(TAG2.lower(), -75)
    iso.emit("aa:bb:cc:dd:ee:ff", -40)  # a device that is not a tag: ignored
    clock.now = 100.1
    step = receivers.read_adverts()
    assert step == [{"receiver": "iso", "rssi_dbm": -70, "offset_s": 0.02, "tag": 1, "address": TAG2},
                    {"receiver": "iso", "rssi_dbm": -60, "offset_s": 0.021, "tag": 0, "address": TAG},
                    {"receiver": "dir", "rssi_dbm": -75, "offset_s": 0.05, "tag": 1, "address": TAG2}]
    assert receivers.collector.duplicates == 1
    m = _valid(step)
    assert m.rssi_dbm("iso") == (-60,) and m.rssi_dbm("iso", tag=1) == (-70,) and m.rssi_dbm("dir", tag=1) == (-75,)
    assert m.advertisements("dir") == ()  # tag 0 was not heard by Rx(dir) this step: no RF evidence of it there


def test_a_campaign_for_fewer_tags_gets_only_those(two_tags):
    receivers, clock, iso, dir_ = two_tags
    receivers.reset(n_tags=1)  # EpisodeStart of a campaign that searches for tag 0 only
    clock.now = 100.03
    iso.emit(TAG2, -70)
    dir_.emit(TAG, -72)
    clock.now = 100.1
    assert receivers.read_adverts() == [{"receiver": "dir", "rssi_dbm": -72, "offset_s": 0.03, "tag": 0, "address": TAG}]
    receivers.reset()  # the next episode's campaign did not say: every tag listened for
    clock.now = 100.13
    iso.emit(TAG2, -71)
    clock.now = 100.2
    assert [(a["tag"], a["rssi_dbm"]) for a in receivers.read_adverts()] == [(1, -71)]


@pytest.mark.parametrize("tags, message", [
    ("E7:8F:13", "'E7:8F:13' is not a BLE address (six hex bytes, e.g. E7:8F:13:56:24:CE) or a beacon identity"),
    ("E7-8F-13-56-24-CE", "'E7-8F-13-56-24-CE' is not a BLE address"),
    ([TAG, TAG.lower()], f"tag address {TAG} given twice"),
    ([], "no tag address given"),
    ("ibeacon:f7826da6-4fa2-4e98-8024", "'ibeacon:f7826da6-4fa2-4e98-8024' is not an iBeacon identity (ibeacon:UUID[:MAJOR[:MINOR]]"),
    (f"ibeacon:{UUID}:1:70000", f"'ibeacon:{UUID}:1:70000' is not an iBeacon identity"),
    ("eddystone:edd1ebeac04e5defa017:0a1b", "'eddystone:edd1ebeac04e5defa017:0a1b' is not an Eddystone-UID identity"),
    ([f"ibeacon:{UUID}:1", f"ibeacon:{UUID.upper()}:1:42"], f"tags ibeacon:{UUID}:1 and ibeacon:{UUID}:1:42 overlap"),
    ([f"ibeacon:{UUID.replace('-', '')}:1:42", f"IBEACON:{UUID}:1:42"], f"tag ibeacon:{UUID}:1:42 given twice"),
])
def test_bad_tag_addresses_are_refused_in_one_line(tags, message):
    with pytest.raises(ValueError) as err:
        ble.BleReceivers(tags, scanner_factory=ble.FakeScanner)
    assert str(err.value).startswith(message) and "\n" not in str(err.value)


def test_a_scanner_that_cannot_start_says_which_and_stops_the_other():
    class NoSecondAdapter(ble.FakeScanner):
        async def start(self) -> None:
            if self.adapter == "hci1":
                raise RuntimeError("No Bluetooth adapter found: hci1")  # what bleak's BleakError says
            await super().start()

    ble.FakeScanner.instances.clear()
    receivers = ble.BleReceivers(TAG, scanner_factory=NoSecondAdapter)
    with pytest.raises(ble.ScannerError) as err:
        receivers.start()
    assert str(err.value) == "Rx(dir) cannot scan on adapter hci1: No Bluetooth adapter found: hci1"
    assert [s.running for s in ble.FakeScanner.instances] == [False, False] and receivers.loop is None  # Rx(iso)'s stopped too

    def no_bleak(callback, adapter):
        raise ImportError("No module named 'bleak'")

    with pytest.raises(ble.ScannerError) as err:
        ble.BleReceivers(TAG, scanner_factory=no_bleak).start()
    assert str(err.value) == "real BLE receivers need bleak (No module named 'bleak'): pip install bleak"


def test_a_node_left_listening_between_episodes_keeps_only_the_newest_advertisements(rig):
    receivers, clock, iso, _ = rig
    receivers.reset()
    for k in range(ble.MAX_PENDING + 500):  # a tag heard for hours while no episode runs: nobody takes the lists
        clock.now = 100.0 + 0.01 * (k + 1)
        iso.emit(TAG, -60 - k % 7)
    assert len(receivers.collector.pending) == ble.MAX_PENDING
    clock.now += 1.0
    step = receivers.read_adverts()
    assert len(step) == ble.MAX_PENDING and step[0]["offset_s"] == pytest.approx(0.01 * 501)  # the oldest 500 went
    _valid(step)  # still one valid step: the protocol allows 10 000


def _ibeacon(uuid: str, major: int, minor: int) -> dict:
    """iBeacon's manufacturer data as bleak reports it: {0x004C: 02 15 UUID major minor power}, written out
    here byte by byte (independent of the driver's ``ibeacon_data``, which the fake tags use)."""
    return {0x004C: bytes([0x02, 0x15]) + bytes.fromhex(uuid.replace("-", "")) + major.to_bytes(2, "big")
            + minor.to_bytes(2, "big") + bytes([0xC5])}


def _eddystone(namespace: str, instance: str) -> dict:
    """An Eddystone-UID frame as bleak reports it: {0xFEAA's 128-bit UUID: 00 power namespace instance 00 00}."""
    return {ble.EDDYSTONE_SERVICE: bytes([0x00, 0xEE]) + bytes.fromhex(namespace) + bytes.fromhex(instance) + bytes(2)}


def test_a_beacon_whose_address_changes_is_followed_by_the_identity_it_advertises():
    """Tags named by what they advertise (an iBeacon by UUID, major and minor; an Eddystone-UID by namespace
    only: any instance) are heard from whatever address they use now (a resolvable private address rotates);
    other beacons of the same UUID, or other frames, are not the tags; the advertisements name the tag and
    no address (the address is not the tag's), and the lists are valid protocol 1.4."""
    clock = Clock()
    ble.FakeScanner.instances.clear()
    namespace = "edd1ebeac04e5defa017"
    receivers = ble.BleReceivers([f"iBeacon:{UUID.upper()}:1:42", f"eddystone:{namespace.upper()}"], scanner_factory=ble.FakeScanner,
                                 clock=clock)
    assert receivers.tags == [f"ibeacon:{UUID}:1:42", f"eddystone:{namespace}"]  # canonical: lower-case hex, numbers as given
    receivers.start()
    iso, dir_ = ble.FakeScanner.instances
    try:
        receivers.reset()
        clock.now = 100.01
        iso.emit("4A:11:22:33:44:55", -60, manufacturer_data=_ibeacon(UUID, 1, 42))
        clock.now = 100.02
        iso.emit("4A:11:22:33:44:56", -61, manufacturer_data=_ibeacon(UUID, 1, 43))  # the same UUID, another minor: not the tag
        iso.emit("4A:11:22:33:44:57", -62, manufacturer_data={0x0059: bytes(23)})  # another company's data
        clock.now = 100.03
        dir_.emit("7B:00:00:00:00:01", -70, service_data=_eddystone(namespace, "0a1b2c3d4e5f"))
        clock.now = 100.04
        dir_.emit("7B:00:00:00:00:02", -71, service_data={ble.EDDYSTONE_SERVICE: bytes([0x10, 0xEE]) + b"url"})  # a URL frame
        clock.now = 100.1
        first = receivers.read_adverts()
        clock.now = 100.15
        iso.emit("5C:99:88:77:66:55", -59, manufacturer_data=_ibeacon(UUID, 1, 42))  # its address rotated: the same tag
        clock.now = 100.2
        second = receivers.read_adverts()
    finally:
        receivers.stop()
    assert first == [{"receiver": "iso", "rssi_dbm": -60, "offset_s": 0.01, "tag": 0},
                     {"receiver": "dir", "rssi_dbm": -70, "offset_s": 0.03, "tag": 1}]
    assert second == [{"receiver": "iso", "rssi_dbm": -59, "offset_s": 0.05, "tag": 0}]
    m = _valid(first + second)
    assert m.rssi_dbm("iso") == (-60, -59) and m.rssi_dbm("dir", tag=1) == (-70,)
    wrapped = ble.with_ble(object(), receivers)
    assert wrapped.n_tags == 2 and wrapped.tag_addresses == []  # EpisodeTruth names no address for such tags


def test_beacon_identities_read_ibeacon_and_eddystone_uid_frames():
    data = type("AdvertisementData", (), {"manufacturer_data": _ibeacon(UUID, 65535, 0),
                                          "service_data": _eddystone("00112233445566778899", "aabbccddeeff")})()
    assert ble.beacon_identities(data) == [f"ibeacon:{UUID}:65535:0", "eddystone:00112233445566778899:aabbccddeeff"]
    short = type("AdvertisementData", (), {"manufacturer_data": {0x004C: bytes([0x02, 0x15, 1, 2])}, "service_data": {}})()
    assert ble.beacon_identities(short) == []  # truncated: no identity, never a guess
    assert ble.ibeacon_data(f"ibeacon:{UUID.upper()}:7:9", power=-59) == _ibeacon(UUID, 7, 9)  # what the fake tags advertise


def test_a_tag_never_heard_in_an_episode_of_5_s_or_more_is_named(two_tags):
    """The node warns at an episode's end about a tag it searched for and never heard (out of range, not
    advertising, or its address rotated): the collector names it once 5 s have passed, not before (a shorter
    episode may fall between two advertisements), and never a tag the episode does not search for."""
    receivers, clock, iso, dir_ = two_tags
    wrapped = ble.with_ble(object(), receivers)
    receivers.reset()
    clock.now = 101.0
    iso.emit(TAG, -60)
    clock.now = 101.1
    assert len(receivers.read_adverts()) == 1
    assert wrapped.silent_tags() == []  # 1 s: too soon to say
    clock.now = 105.5
    receivers.read_adverts()
    assert wrapped.silent_tags() == [(1, TAG2)]
    receivers.reset(n_tags=1)  # an episode for tag 0 only: tag 1's silence is not a problem
    clock.now = 111.0
    iso.emit(TAG, -61)
    clock.now = 111.1
    assert len(receivers.read_adverts()) == 1
    assert wrapped.silent_tags() == []


class _Beacons(ble.FakeScanner):
    """A scanner that hears, as it starts: a tag by its address (20 events, each reported twice within 5 ms),
    an iBeacon from two rotating addresses, and one report without an RSSI."""

    clock = Clock()

    async def start(self) -> None:
        self.running = True
        c = _Beacons.clock
        for k in range(20):
            c.now += 0.5
            self.emit(TAG, -60 - k % 3)
            c.now += 0.001
            self.emit(TAG.lower(), -60)  # the same event reported again: counted once
            self.emit(f"4A:00:00:00:00:0{k % 2}", -75, manufacturer_data=_ibeacon(UUID, 1, 42))
        self.emit("11:22:33:44:55:66", -127)  # no RSSI: not a device heard


def test_scan_lists_the_devices_heard_loudest_first_with_their_rate_and_identity(capsys):
    """``python ble_receiver.py scan`` (for finding a tag's --ble-tag and checking the adapter reports every
    advertisement): one row per address, the loudest first, its advertisements per second (a report within 5 ms of
    the previous one is the same event), its median RSSI and the beacon identity it advertises."""
    _Beacons.clock.now = 0.0
    rows = ble.scan(2.0, "hci0", scanner_factory=_Beacons, clock=_Beacons.clock)
    assert [(r["address"], r["per_second"], r["median_rssi_dbm"], r["identities"]) for r in rows] == [
        (TAG, 10.0, -61, []), ("4A:00:00:00:00:00", 5.0, -75, [f"ibeacon:{UUID}:1:42"]),
        ("4A:00:00:00:00:01", 5.0, -75, [f"ibeacon:{UUID}:1:42"])]
    _Beacons.clock.now = 0.0
    assert ble.main(["scan", "--seconds", "0.5", "--adapter", "hci1"], scanner_factory=_Beacons, clock=_Beacons.clock) == 0
    assert ble.FakeScanner.instances[-1].adapter == "hci1"
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == ["address", "adverts/s", "median", "dBm", "beacon", "identity", "(--ble-tag)", "name"]
    assert [line.split()[:4] for line in out[1:]] == [[TAG, "40.00", "-61", "-"], ["4A:00:00:00:00:00", "20.00", "-75", f"ibeacon:{UUID}:1:42"],
                                                      ["4A:00:00:00:00:01", "20.00", "-75", f"ibeacon:{UUID}:1:42"]]


def test_scan_says_in_one_line_why_it_cannot_listen(capsys):
    class NoAdapter(ble.FakeScanner):
        async def start(self) -> None:
            raise RuntimeError("No Bluetooth adapters found.")

    assert ble.main(["scan", "--seconds", "0.01"], scanner_factory=NoAdapter) == 1
    assert capsys.readouterr().err == "error: cannot scan on adapter hci0: No Bluetooth adapters found.\n"
    with pytest.raises(SystemExit) as exit_:
        ble.main(["scan", "--seconds", "0"])
    assert exit_.value.code == 2 and "--seconds: expected a number in (0, 3600]" in capsys.readouterr().err
