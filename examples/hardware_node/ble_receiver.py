#!/usr/bin/env python3
"""A BLE receiver driver for the hardware node (protocol 1.3, docs/protocol.md "Measurement"):
two scanners, Rx(iso) and Rx(dir), listen for the advertisements of one tag, or of several (protocol
1.4, docs/tags.md: tag k is the k-th address given), and each control step the node takes *every
advertisement heard since the previous step*, possibly none.

Built on bleak (https://bleak.readthedocs.io; ``pip install bleak``, an optional dependency):
``BleakScanner(detection_callback, adapter=...)`` calls back with ``(BLEDevice, AdvertisementData)``
for every advertisement; ``device.address`` names the sender, ``advertisement_data.rssi`` is the
RSSI in whole dBm. Imports nothing from ra2vipas, and nothing from bleak until a real scanner is
started: the tests run it on ``FakeScanner`` (no BLE adapter needed). ``python ble_receiver.py scan``
lists the devices an adapter hears (address, advertisements per second, median RSSI, beacon identity):
what ``--ble-tag`` takes, and whether every advertisement is reported.

How the callback stream becomes per-step lists (``AdvertCollector``):

* only the tags count; every other device is ignored. A tag is named by its address (case-insensitive)
  or, for a beacon whose address changes (a resolvable private address, rotated every few minutes),
  by the identity it advertises: ``ibeacon:UUID[:MAJOR[:MINOR]]`` (Apple's manufacturer data, company
  0x004C, type 0x02 0x15) or ``eddystone:NAMESPACE[:INSTANCE]`` (an Eddystone-UID frame, service data
  of 0xFEAA), read from bleak's ``AdvertisementData.manufacturer_data`` / ``service_data``; a shorter
  identity matches every beacon that extends it. With several tags each advertisement also names its
  tag (``tag``: k) and, for a tag named by its address, that address (``address``, upper case; a
  beacon named by its identity sends none: its address is not the tag's), and a campaign that
  searches for fewer tags (the scenario's ``n_tags``) gets only tags 0 .. n_tags - 1; with one tag
  the lists are protocol 1.3's, byte for byte;
* each advertisement is stamped on arrival with the node's clock and belongs to the step whose
  window (the previous ``take`` to this one) it arrived in, ``offset_s`` after that window opened;
* **duplicates**: a second report of the same tag from the same receiver within ``duplicate_window_s``
  (5 ms, less than BLE's shortest advertising interval, 20 ms) of the previous one is the same
  advertising event heard twice (another channel, or the stack reporting it again) and is dropped
  (two tags advertising within 5 ms of each other are two packets);
* **late**: a report stamped before the current window opened (a callback the event loop ran
  after the step was cut) is carried by the current step at offset 0, never dropped or moved back;
* **lost**: nothing arrives, and the step's list is empty: no RSSI is made up;
* **no RSSI**: a report whose RSSI is bleak's -127 (BlueZ had none for the device: HCI's "not
  available", 127) is dropped, not read as a -127 dBm packet;
* **idle**: between episodes nobody takes the lists, so only the newest ``MAX_PENDING`` (10 000, what
  one step may carry) are kept: a node left listening for days does not grow.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import logging
import re
import statistics
import sys
import threading
import time
from typing import Any, Callable, Sequence

log = logging.getLogger("ble-receiver")

DUPLICATE_WINDOW_S = 0.005
NO_RSSI = -127  # what bleak reports when BlueZ has no RSSI for the device (HCI says 127: "not available")
MAX_PENDING = 10_000  # advertisements kept untaken (protocol: at most 10 000 per step)
ADDRESS = re.compile(r"^[0-9A-Fa-f]{2}(:[0-9A-Fa-f]{2}){5}$")  # what BlueZ reports: six bytes, colon-separated
IBEACON_COMPANY = 0x004C  # Apple: iBeacon's manufacturer data starts 0x02 0x15, then UUID (16), major (2), minor (2), power (1)
EDDYSTONE_SERVICE = "0000feaa-0000-1000-8000-00805f9b34fb"  # Eddystone's service data; frame 0x00 (UID): power, namespace (10), instance (6)
_UUID = re.compile(r"^[0-9a-f]{8}-?[0-9a-f]{4}-?[0-9a-f]{4}-?[0-9a-f]{4}-?[0-9a-f]{12}$")
_HEX = re.compile(r"^[0-9a-f]*$")
BAD_TAG = ("is not a BLE address (six hex bytes, e.g. E7:8F:13:56:24:CE) or a beacon identity (ibeacon:UUID[:MAJOR[:MINOR]], "
           "eddystone:NAMESPACE[:INSTANCE])")


def _uuid(hex32: str) -> str:
    return f"{hex32[:8]}-{hex32[8:12]}-{hex32[12:16]}-{hex32[16:20]}-{hex32[20:]}"


def parse_tag(text: str) -> str:
    """One tag as ``--ble-tag`` names it, in its canonical form: an address (upper case), or a beacon
    identity ``ibeacon:uuid[:major[:minor]]`` / ``eddystone:namespace[:instance]`` (lower-case hex);
    ValueError (one line) for anything else."""
    t = str(text).strip()
    if ADDRESS.match(t):
        return t.upper()
    kind, _, rest = t.partition(":")
    parts = rest.lower().split(":") if rest else []
    if kind.lower() == "ibeacon" and 1 <= len(parts) <= 3 and _UUID.match(parts[0]) \
            and all(p.isdigit() and int(p) <= 65535 for p in parts[1:]):
        return "ibeacon:" + ":".join([_uuid(parts[0].replace("-", ""))] + [str(int(p)) for p in parts[1:]])
    if kind.lower() == "eddystone" and 1 <= len(parts) <= 2 and len(parts[0]) == 20 and _HEX.match(parts[0]) \
            and all(len(p) == 12 and _HEX.match(p) for p in parts[1:]):
        return "eddystone:" + ":".join(parts)
    if kind.lower() == "ibeacon":
        raise ValueError(f"{t!r} is not an iBeacon identity (ibeacon:UUID[:MAJOR[:MINOR]], MAJOR and MINOR 0-65535, "
                         f"e.g. ibeacon:f7826da6-4fa2-4e98-8024-bc5b71e0893e:1:42)")
    if kind.lower() == "eddystone":
        raise ValueError(f"{t!r} is not an Eddystone-UID identity (eddystone:NAMESPACE[:INSTANCE], 10 and 6 hex bytes, "
                         f"e.g. eddystone:edd1ebeac04e5defa017:0a1b2c3d4e5f)")
    raise ValueError(f"{t!r} {BAD_TAG}")


def tag_addresses(addresses: str | Sequence[str]) -> list[str]:
    """The tags (``parse_tag``), tag k the k-th; ValueError (one line) for one that is malformed, given
    twice, or a beacon identity that another one's beacons would match too."""
    given = [addresses] if isinstance(addresses, str) else list(addresses)
    if not given:
        raise ValueError("no tag address given")
    out: list[str] = []
    for text in given:
        tag = parse_tag(text)
        if tag in out:
            raise ValueError(f"tag {'address ' if ADDRESS.match(tag) else ''}{tag} given twice")
        for other in out:
            if tag.startswith(other + ":") or other.startswith(tag + ":"):
                raise ValueError(f"tags {other} and {tag} overlap: one beacon would be both (name each by its whole identity)")
        out.append(tag)
    return out


def beacon_identities(advertisement_data) -> list[str]:
    """The beacon identities an advertisement carries (``parse_tag``'s canonical form): iBeacon's
    ``ibeacon:uuid:major:minor`` and Eddystone-UID's ``eddystone:namespace:instance``."""
    out = []
    apple = (getattr(advertisement_data, "manufacturer_data", None) or {}).get(IBEACON_COMPANY)
    if apple and len(apple) >= 22 and apple[0] == 0x02 and apple[1] == 0x15:
        out.append(f"ibeacon:{_uuid(bytes(apple[2:18]).hex())}:{int.from_bytes(apple[18:20], 'big')}:"
                   f"{int.from_bytes(apple[20:22], 'big')}")
    eddystone = (getattr(advertisement_data, "service_data", None) or {}).get(EDDYSTONE_SERVICE)
    if eddystone and len(eddystone) >= 18 and eddystone[0] == 0x00:
        out.append(f"eddystone:{bytes(eddystone[2:12]).hex()}:{bytes(eddystone[12:18]).hex()}")
    return out


def ibeacon_data(identity: str, power: int = -59) -> dict[int, bytes]:
    """What an iBeacon of ``identity`` (``ibeacon:uuid:major:minor``) advertises, as bleak's
    ``manufacturer_data``: ``beacon_identities``' inverse, for a fake tag (tests, ``FakeScanner``)."""
    _, uuid, major, minor = parse_tag(identity).split(":")
    return {IBEACON_COMPANY: bytes([0x02, 0x15]) + bytes.fromhex(uuid.replace("-", "")) + int(major).to_bytes(2, "big")
            + int(minor).to_bytes(2, "big") + (power & 0xFF).to_bytes(1, "big")}


class AdvertCollector:
    """Thread-safe: ``add`` from the scanners' callbacks, ``take`` once per control step."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, duplicate_window_s: float = DUPLICATE_WINDOW_S,
                 addresses: Sequence[str] | None = None) -> None:
        self.clock = clock
        self.duplicate_window_s = duplicate_window_s
        self.addresses = list(addresses or [])  # several: each advert names its tag and address (protocol 1.4)
        self.lock = threading.Lock()
        self.pending: collections.deque[tuple[float, str, int, int | None, int]] = collections.deque(maxlen=MAX_PENDING)
        self.last: dict[tuple[str, int], float] = {}
        self.window_start = clock()
        self.wanted = max(len(self.addresses), 1)  # the tags the current campaign searches for
        self.duplicates = 0
        self.late = 0
        self.unavailable = 0  # reports without an RSSI (bleak's -127): dropped, never a reading
        self.heard: collections.Counter[int] = collections.Counter()  # this episode's advertisements sent, per tag
        self.listening_since = self.window_start

    def reset(self, n_tags: int | None = None) -> None:
        """Start a new episode: forget what was heard; the first step's window opens now. ``n_tags``: the
        campaign's (its scenario's), only tags 0 .. n_tags - 1 are sent (None: every tag listened for)."""
        with self.lock:
            self.pending.clear()
            self.last.clear()
            self.window_start = self.listening_since = self.clock()
            self.wanted = max(len(self.addresses), 1) if n_tags is None else int(n_tags)
            self.heard.clear()

    def add(self, receiver: str, rssi_dbm: int, at: float | None = None, channel: int | None = None, tag: int = 0) -> None:
        """One advertisement of tag ``tag`` heard by ``receiver`` (``iso``|``dir``), stamped ``at`` (now if None)."""
        stamp = self.clock() if at is None else at
        with self.lock:
            previous = self.last.get((receiver, tag))
            if previous is not None and abs(stamp - previous) < self.duplicate_window_s:
                self.duplicates += 1
                return
            self.last[(receiver, tag)] = stamp
            self.pending.append((stamp, receiver, int(rssi_dbm), channel, int(tag)))

    def take(self, now: float | None = None) -> list[dict[str, Any]]:
        """The advertisements heard since the previous ``take`` (the step's ``adverts``, in arrival
        order, maybe none); the next step's window opens at ``now``."""
        cut = self.clock() if now is None else now
        with self.lock:
            start, wanted = self.window_start, self.wanted
            mine = [p for p in self.pending if p[0] < cut]
            self.pending = collections.deque((p for p in self.pending if p[0] >= cut), maxlen=MAX_PENDING)
            self.window_start = cut
        several = len(self.addresses) > 1
        out = []
        for stamp, receiver, rssi, channel, tag in sorted(mine, key=lambda p: p[0]):
            if tag >= wanted:
                continue  # a tag the campaign does not search for
            if stamp < start:
                self.late += 1
            advert: dict[str, Any] = {"receiver": receiver, "rssi_dbm": rssi, "offset_s": round(max(0.0, stamp - start), 6)}
            if channel in (37, 38, 39):
                advert["channel"] = channel
            self.heard[tag] += 1
            if several:  # protocol 1.4: which tag, from which address (a beacon named by its identity: none)
                advert["tag"] = tag
                if ADDRESS.match(self.addresses[tag]):
                    advert["address"] = self.addresses[tag]
            out.append(advert)
        return out


    def silent(self, after_s: float = 5.0) -> list[int]:
        """The tags this episode searches for that sent nothing since it began, once it has listened
        ``after_s`` seconds (a shorter episode may simply have been between two advertisements)."""
        if self.clock() - self.listening_since < after_s:
            return []
        return [k for k in range(self.wanted) if not self.heard[k]]


def bleak_scanner(detection_callback, adapter: str | None):
    """A real scanner: bleak's ``BleakScanner`` on BlueZ adapter ``adapter`` (e.g. ``hci0``), asking BlueZ
    for every advertisement: bleak sets BlueZ's discovery filter ``DuplicateData`` to false, so BlueZ
    reports a beacon again only when its data changes, and a beacon whose payload never changes
    would be heard about once (bleak's ``BlueZDiscoveryFilters``); the driver sets it to true."""
    from bleak import BleakScanner  # optional: only a real receiver needs it

    bluez: dict[str, Any] = {"filters": {"DuplicateData": True}}
    kwargs: dict[str, Any] = {"detection_callback": detection_callback, "bluez": bluez}
    if adapter:
        try:  # bleak 3 takes the adapter in its BlueZ arguments (the keyword is deprecated there)
            from bleak.args.bluez import BlueZScannerArgs
            in_bluez = "adapter" in getattr(BlueZScannerArgs, "__annotations__", {})
        except ImportError:
            in_bluez = False
        if in_bluez:
            bluez["adapter"] = adapter
        else:
            kwargs["adapter"] = adapter
    return BleakScanner(**kwargs)


class BleReceivers:
    """Rx(iso) and Rx(dir) as two scanners (two adapters) listening for ``tags``: one address or beacon
    identity, or several (tag k the k-th; ValueError for a malformed, repeated or overlapping one,
    ``tag_addresses``).

    ``scanner_factory(detection_callback, adapter)`` builds a scanner with ``async start()`` and
    ``async stop()`` (bleak's ``BleakScanner`` by default; ``FakeScanner`` in tests). The scanners
    run on an asyncio loop in a thread of their own; ``read_adverts()`` is the node's per-step call.
    """

    def __init__(self, tags: str | Sequence[str], adapters: dict[str, str | None] | None = None,
                 scanner_factory: Callable = bleak_scanner, clock: Callable[[], float] = time.monotonic) -> None:
        self.tags = tag_addresses(tags)
        self.index = {tag.lower(): k for k, tag in enumerate(self.tags) if ADDRESS.match(tag)}
        self.beacons = [(tag, k) for k, tag in enumerate(self.tags) if not ADDRESS.match(tag)]  # named by identity
        self.adapters = adapters or {"iso": "hci0", "dir": "hci1"}
        self.factory = scanner_factory
        self.collector = AdvertCollector(clock, addresses=self.tags)
        self.scanners: dict[str, Any] = {}
        self.loop: asyncio.AbstractEventLoop | None = None
        self.thread: threading.Thread | None = None

    def callback_for(self, receiver: str):
        def detected(device, advertisement_data) -> None:
            tag = self.index.get(str(getattr(device, "address", "")).lower())
            if tag is None and self.beacons:  # a beacon named by what it advertises, whatever its address now
                tag = next((k for identity in beacon_identities(advertisement_data) for spec, k in self.beacons
                            if identity == spec or identity.startswith(spec + ":")), None)
            if tag is None:
                return
            rssi = getattr(advertisement_data, "rssi", None)
            if rssi is None or not NO_RSSI < int(rssi) < -NO_RSSI:  # bleak's -127 (HCI's 127): no RSSI, not a reading
                self.collector.unavailable += 1
                return
            self.collector.add(receiver, int(rssi), tag=tag)
        return detected

    def start(self, timeout: float = 10.0) -> None:
        """Start both scanners on a background event loop; if one cannot start, stop what started and
        raise ``ScannerError`` (one line naming the receiver and its adapter)."""
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="ble-scanners", daemon=True)
        self.thread.start()
        for receiver, adapter in self.adapters.items():
            try:
                scanner = self.factory(self.callback_for(receiver), adapter)
                asyncio.run_coroutine_threadsafe(scanner.start(), self.loop).result(timeout)
            except ImportError as err:
                self.stop()
                raise ScannerError(f"real BLE receivers need bleak ({err}): pip install bleak") from err
            except Exception as err:  # bleak's BleakError (no such adapter, BlueZ not running, not allowed), a timeout
                self.stop()
                raise ScannerError(f"Rx({receiver}) cannot scan on adapter {adapter or 'default'}: "
                                   f"{str(err).strip() or type(err).__name__}") from err
            self.scanners[receiver] = scanner

    def stop(self, timeout: float = 10.0) -> None:
        """Stop the scanners and their loop."""
        if self.loop is None:
            return
        for scanner in self.scanners.values():
            try:
                asyncio.run_coroutine_threadsafe(scanner.stop(), self.loop).result(timeout)
            except Exception as err:  # a scanner that fails to stop must not keep the node from exiting
                log.warning("stopping a scanner failed: %s", err)
        self.loop.call_soon_threadsafe(self.loop.stop)
        if self.thread is not None:
            self.thread.join(timeout)
        self.loop.close()
        self.loop = None

    def reset(self, n_tags: int | None = None) -> None:
        self.collector.reset(n_tags)

    def read_adverts(self) -> list[dict[str, Any]]:
        """Every advertisement of the tag heard since the previous call: the step's ``adverts``."""
        return self.collector.take()


class ScannerError(RuntimeError):
    """A receiver's scanner could not start (no bleak, no such adapter, BlueZ not running): one line."""


class _WithBle:
    """A driver whose RF comes from BLE receivers: ``read_adverts``/``reset_adverts`` instead of ``read_rssi``."""

    def __init__(self, driver, receivers: BleReceivers) -> None:
        self._driver, self._receivers = driver, receivers

    def __getattr__(self, name: str):
        if name == "read_rssi":
            raise AttributeError(name)
        return getattr(self._driver, name)

    @property
    def n_tags(self) -> int:
        """How many tags the receivers listen for (more than one: protocol 1.4)."""
        return len(self._receivers.tags)

    @property
    def tag_addresses(self) -> list[str]:
        """The tags' addresses, tag k the k-th (upper case); none when a tag is named by its beacon identity
        (its address is not the tag's)."""
        tags = list(self._receivers.tags)
        return tags if all(ADDRESS.match(t) for t in tags) else []

    def read_adverts(self) -> list[dict[str, Any]]:
        return self._receivers.read_adverts()

    def silent_tags(self) -> list[tuple[int, str]]:
        """(k, tag) of each tag the episode searches for that sent nothing in its 5 s or more."""
        return [(k, self._receivers.tags[k]) for k in self._receivers.collector.silent() if k < len(self._receivers.tags)]

    def reset_adverts(self, n_tags: int | None = None) -> None:
        self._receivers.reset(n_tags)


def with_ble(driver, receivers: BleReceivers):
    """``driver`` (pan unit, camera) with its RF read from ``receivers``."""
    return _WithBle(driver, receivers)


class FakeScanner:
    """bleak's scanner interface without a radio: ``emit`` plays an advertisement into the callback."""

    instances: list["FakeScanner"] = []

    def __init__(self, detection_callback, adapter: str | None = None) -> None:
        self.callback = detection_callback
        self.adapter = adapter
        self.running = False
        FakeScanner.instances.append(self)

    async def start(self) -> None:
        self.running = True

    async def stop(self) -> None:
        self.running = False

    def emit(self, address: str, rssi: int, manufacturer_data: dict | None = None, service_data: dict | None = None) -> None:
        if self.running:
            device = type("BLEDevice", (), {"address": address})()
            data = type("AdvertisementData", (), {"rssi": rssi, "manufacturer_data": manufacturer_data or {},
                                                  "service_data": service_data or {}})()
            self.callback(device, data)


class DeviceSurvey:
    """What a scanner hears, per address (``callback`` is its detection callback): how many
    advertisements (a report within 5 ms of the previous one is the same event, as the node counts),
    their RSSI, the beacon identities and the name they carry. For finding a tag's ``--ble-tag``
    and checking the adapter reports every advertisement (``python ble_receiver.py scan``)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.lock = threading.Lock()
        self.seen: dict[str, dict[str, Any]] = {}

    def callback(self, device, advertisement_data) -> None:
        rssi = getattr(advertisement_data, "rssi", None)
        if rssi is None or not NO_RSSI < int(rssi) < -NO_RSSI:
            return
        now = self.clock()
        address = str(getattr(device, "address", "")).upper()
        with self.lock:
            d = self.seen.setdefault(address, {"rssi": [], "last": None, "identities": set(), "name": None})
            if d["last"] is not None and now - d["last"] < DUPLICATE_WINDOW_S:
                return
            d["last"] = now
            d["rssi"].append(int(rssi))
            d["identities"].update(beacon_identities(advertisement_data))
            d["name"] = getattr(advertisement_data, "local_name", None) or d["name"]

    def rows(self, seconds: float) -> list[dict[str, Any]]:
        """One row per address, the loudest first: address, advertisements per second, median RSSI [dBm],
        beacon identities, name."""
        with self.lock:
            rows = [{"address": a, "per_second": len(d["rssi"]) / max(seconds, 1e-9), "median_rssi_dbm": statistics.median(d["rssi"]),
                     "identities": sorted(d["identities"]), "name": d["name"]} for a, d in self.seen.items() if d["rssi"]]
        return sorted(rows, key=lambda r: (-r["median_rssi_dbm"], r["address"]))


def scan(seconds: float, adapter: str | None = None, scanner_factory: Callable = bleak_scanner,
         clock: Callable[[], float] = time.monotonic) -> list[dict[str, Any]]:
    """Listen ``seconds`` on ``adapter`` and return ``DeviceSurvey.rows``; ``ScannerError`` (one line) if
    the scanner cannot start."""
    survey = DeviceSurvey(clock)
    loop = asyncio.new_event_loop()
    try:
        try:
            scanner = scanner_factory(survey.callback, adapter)
            loop.run_until_complete(scanner.start())
        except ImportError as err:
            raise ScannerError(f"real BLE receivers need bleak ({err}): pip install bleak") from err
        except Exception as err:  # bleak's BleakError: no such adapter, BlueZ not running, not allowed
            raise ScannerError(f"cannot scan on adapter {adapter or 'default'}: {str(err).strip() or type(err).__name__}") from err
        try:
            loop.run_until_complete(asyncio.sleep(seconds))
        finally:
            loop.run_until_complete(scanner.stop())
    finally:
        loop.close()
    return survey.rows(seconds)


def main(argv: Sequence[str] | None = None, scanner_factory: Callable = bleak_scanner, clock: Callable[[], float] = time.monotonic) -> int:
    """``python ble_receiver.py scan [--seconds S] [--adapter hciN]``: every BLE device the adapter hears,
    the loudest first, with its advertisements per second (to compare with the tag's advertising rate),
    its median RSSI and the beacon identities it advertises (what ``--ble-tag`` takes)."""
    parser = argparse.ArgumentParser(prog="ble_receiver.py", description="List the BLE devices an adapter hears, to find a tag's "
                                     "--ble-tag (its address or beacon identity) and check every advertisement is reported.")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("scan", help="listen and list every device heard, the loudest first")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to listen [s] (default 10)")
    p.add_argument("--adapter", default="hci0", help="the BlueZ adapter (default hci0)")
    args = parser.parse_args(argv)
    if not 0.0 < args.seconds <= 3600.0:
        parser.error("--seconds: expected a number in (0, 3600]")
    try:
        rows = scan(args.seconds, args.adapter, scanner_factory, clock)
    except ScannerError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    if not rows:
        print(f"nothing heard in {args.seconds:g} s on {args.adapter}")
        return 0
    print(f"{'address':<17}  {'adverts/s':>9}  {'median dBm':>10}  beacon identity (--ble-tag)  name")
    for r in rows:
        print(f"{r['address']:<17}  {r['per_second']:>9.2f}  {r['median_rssi_dbm']:>10g}  {', '.join(r['identities']) or '-'}  {r['name'] or ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
