"""Recorded channel files: real BLE recordings, compacted, for the ``recorded`` radio
(issue 20; docs/radio.md, "Recorded channel files").

A channel file is a compressed numpy archive (``.npz``, read with ``allow_pickle=False``):

* ``meta``: JSON text: ``source``, ``licence``, ``credit``, ``command`` (the importer's command
  that rebuilt it), ``receivers`` (names), ``fit`` (the pooled log-distance fit: ``kappa_dbm``,
  ``exponent``), ``sensitivity_dbm`` (the lowest RSSI any recording holds);
* ``rx_pos`` (R, 3) the receivers' positions [m];
* ``rec_receiver`` (M,) which receiver each recording is of; ``rec_point`` (M, 3) where the beacon
  stood [m]; ``rec_start`` (M + 1,) where each recording's packets start in ``gap_ms``/``rssi``;
  ``rec_seconds`` (M,) how long each recording lasts (its first packet at 0);
* ``gap_ms`` (P,) uint16: each packet's time after the previous one of its recording (the first:
  after the recording's start) [ms]; ``rssi`` (P,) int8: its RSSI [dBm] as the receiver reported.

``import_recordings`` builds one from a recording in the dataset's format: ``.mbd`` files, one
per (receiver, beacon position), lines ``timestamp,receiver MAC,beacon MAC,rssi`` (Unix seconds,
integer dBm), named ``<receiver>_<x>_<y>_<z>.mbd``; and the receivers' positions (the dataset's
``tetam.dev``: ``Dongles:{mac: [[x, y, z], colour, name], ...}``, or a CSV ``name,x,y,z``).
Pure Python and numpy.
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DATA_DIR = Path(__file__).resolve().parent / "data"
CHANNELS_ENV = "RA2VIPAS_CHANNELS"
"""Colon-separated folders searched for ``<name>.npz`` after the shipped ones."""
_MBD_NAME = re.compile(r"^(?P<rx>[A-Za-z0-9-]+)_(?P<x>-?[0-9.]+)_(?P<y>-?[0-9.]+)_(?P<z>-?[0-9.]+)\.mbd$")
_MAC = re.compile(r"^[0-9A-Fa-f:]{1,17}$")


class ChannelFileError(ValueError):
    """A recording or channel file could not be read; the message names the file and, for a
    malformed line, its number."""


@dataclass(frozen=True)
class Recording:
    receiver: int
    point: tuple[float, float, float]
    times_s: np.ndarray  # (n,) from the recording's first packet
    rssi: np.ndarray  # (n,) int


@dataclass(frozen=True)
class ChannelFile:
    meta: dict
    rx_pos: np.ndarray
    rec_receiver: np.ndarray
    rec_point: np.ndarray
    rec_start: np.ndarray
    rec_seconds: np.ndarray
    gap_ms: np.ndarray
    rssi: np.ndarray

    @property
    def receivers(self) -> list[str]:
        return list(self.meta["receivers"])

    def times_s(self, m: int) -> np.ndarray:
        lo, hi = int(self.rec_start[m]), int(self.rec_start[m + 1])
        return np.cumsum(self.gap_ms[lo:hi].astype(np.int64)) / 1000.0

    def rssi_of(self, m: int) -> np.ndarray:
        return self.rssi[int(self.rec_start[m]):int(self.rec_start[m + 1])].astype(np.int64)

    def distances_m(self) -> np.ndarray:
        """(M,) the 3-D distance between each recording's beacon and its receiver."""
        return np.linalg.norm(self.rec_point - self.rx_pos[self.rec_receiver], axis=1)


# -- reading the dataset's format ----------------------------------------------------------------

def read_devices(path: Path) -> dict[str, tuple[str, tuple[float, float, float]]]:
    """Receivers by MAC (lower case, no colons): (name, position). ``tetam.dev`` format or CSV ``name,x,y,z[,mac]``."""
    try:
        text = Path(path).read_text()
    except OSError as err:
        raise ChannelFileError(f"cannot read {path}: {err.strerror or err}") from None
    out: dict[str, tuple[str, tuple[float, float, float]]] = {}
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.startswith("Dongles:"):
            try:
                dongles = json.loads(line.removeprefix("Dongles:"))
                for mac, (pos, _colour, name) in dongles.items():
                    out[_mac(mac)] = (str(name), (float(pos[0]), float(pos[1]), float(pos[2])))
            except (ValueError, TypeError, IndexError) as err:
                raise ChannelFileError(f"{path}:{number}: malformed Dongles line ({err})") from None
            continue
        if line.startswith("Beacons:"):
            continue
        parts = [p.strip() for p in line.split(",")]
        try:
            name, x, y, z = parts[0], float(parts[1]), float(parts[2]), float(parts[3])
        except (ValueError, IndexError):
            raise ChannelFileError(f"{path}:{number}: expected 'name,x,y,z[,mac]', got {line[:80]!r}") from None
        out[_mac(parts[4]) if len(parts) > 4 else name] = (name, (x, y, z))
    if not out:
        raise ChannelFileError(f"{path}: no receivers in it")
    return out


def _mac(text: str) -> str:
    return text.strip().lower().replace(":", "")


def read_mbd(path: Path, seconds: float | None = None) -> tuple[str, np.ndarray, np.ndarray]:
    """(receiver MAC, times from the first packet [s], integer RSSI) of one ``.mbd`` file, its
    first ``seconds`` only if given.

    Raises
    ------
    ChannelFileError
        A line that is not ``timestamp,receiver,beacon,rssi`` (a number, a MAC, a MAC, an
        integer), with its file and line number; a file with no packet or two receivers.
    """
    times: list[float] = []
    rssi: list[int] = []
    receiver = None
    try:
        handle = open(path, encoding="utf-8", errors="strict")
    except OSError as err:
        raise ChannelFileError(f"cannot read {path}: {err.strerror or err}") from None
    with handle:
        try:
            for number, line in enumerate(handle, 1):
                line = line.strip()
                if not line:
                    continue
                parts = line.split(",")
                try:
                    if len(parts) < 4:
                        raise ValueError
                    t, rx, value = float(parts[0]), parts[1].strip(), int(parts[3])
                    if not math.isfinite(t) or not _MAC.match(rx) or not _MAC.match(parts[2].strip()) or not -128 <= value <= 20:
                        raise ValueError
                except ValueError:
                    raise ChannelFileError(f"{path}:{number}: expected 'timestamp,receiver,beacon,rssi' (seconds, MAC, MAC, "
                                           f"integer dBm), got {line[:80]!r}") from None
                if receiver is None:
                    receiver = _mac(rx)
                elif _mac(rx) != receiver:
                    raise ChannelFileError(f"{path}:{number}: a second receiver {rx!r} (one receiver per file)")
                if times and t < times[-1]:
                    raise ChannelFileError(f"{path}:{number}: timestamp {parts[0]} goes back in time")
                if seconds is not None and times and t - times[0] > seconds:
                    break
                times.append(t)
                rssi.append(value)
        except UnicodeDecodeError:
            raise ChannelFileError(f"{path}: not a text file") from None
    if not times:
        raise ChannelFileError(f"{path}: no packet in it")
    t = np.asarray(times)
    return receiver, t - t[0], np.asarray(rssi, dtype=np.int64)


def import_recordings(recordings: list[Path], devices: Path, out: Path, *, receivers: list[str] | None = None,
                      seconds: float | None = None, max_range_m: float | None = None, command: str = "") -> ChannelFile:
    """Read ``.mbd`` ``recordings`` (beacon positions from their names) and the receivers'
    positions from ``devices``, keep those of ``receivers`` (names; all if None), the first
    ``seconds`` of each and the points within ``max_range_m`` of their receiver, and write the
    channel file ``out`` (atomically: nothing is written when anything fails).

    Raises
    ------
    ChannelFileError
        A malformed line (file and line number), a file name without a position, a receiver
        the devices do not know, nothing left to write, or the output not writable.
    """
    known = read_devices(devices)
    names = sorted({name for name, _ in known.values()})
    if receivers:
        unknown = [r for r in receivers if r not in names]
        if unknown:
            raise ChannelFileError(f"unknown receiver(s) {', '.join(unknown)}; {devices} has {', '.join(names)}")
    by_name = {name: (mac, pos) for mac, (name, pos) in known.items()}
    chosen = sorted(receivers) if receivers else names
    index = {name: i for i, name in enumerate(chosen)}
    recs: list[Recording] = []
    for path in sorted(recordings, key=lambda p: p.name):
        match = _MBD_NAME.match(path.name)
        if match is None:
            raise ChannelFileError(f"{path}: the name must be <receiver>_<x>_<y>_<z>.mbd (the beacon's position)")
        name = match["rx"]
        if name not in by_name:
            raise ChannelFileError(f"{path}: receiver {name!r} is not in {devices}")
        if name not in index:
            continue
        point = (float(match["x"]), float(match["y"]), float(match["z"]))
        if max_range_m is not None and math.dist(point, by_name[name][1]) > max_range_m:
            continue
        mac, times, rssi = read_mbd(path, seconds)
        if by_name[name][0] != name and mac != by_name[name][0]:
            raise ChannelFileError(f"{path}: its packets come from receiver {mac}, the devices say {name} is {by_name[name][0]}")
        recs.append(Recording(receiver=index[name], point=point, times_s=times, rssi=rssi))
    if not recs:
        raise ChannelFileError("no recording left to write (check the receivers and --max-range)")
    channel = _build(recs, [by_name[n][1] for n in chosen], chosen, command)
    save(channel, out)
    return channel


def _build(recs: list[Recording], positions, names: list[str], command: str) -> ChannelFile:
    gaps, rssi, start, secs = [], [], [0], []
    for r in recs:
        g = np.diff(np.round(r.times_s * 1000.0).astype(np.int64), prepend=0)
        g = np.minimum(g, 65535)
        gaps.append(g.astype(np.uint16))
        rssi.append(r.rssi.astype(np.int8))
        start.append(start[-1] + len(g))
        secs.append(float(r.times_s[-1]) + float(np.median(np.diff(r.times_s))) if len(r.times_s) > 1 else 1.0)
    rx_pos = np.asarray(positions, dtype=np.float32)
    rec_receiver = np.asarray([r.receiver for r in recs], dtype=np.int16)
    rec_point = np.asarray([r.point for r in recs], dtype=np.float32)
    dist = np.linalg.norm(rec_point - rx_pos[rec_receiver], axis=1)
    means = np.asarray([float(np.mean(r.rssi)) for r in recs])
    x = np.log10(np.maximum(dist, 0.1))
    fit = None  # the pooled log-distance fit, RSSI = kappa - 10 n log10(d): needs two distances
    if np.ptp(x) > 0.0:
        slope, intercept = np.polyfit(x, means, 1)
        fit = {"kappa_dbm": round(float(intercept), 2), "exponent": round(float(-slope / 10.0), 3)}
    meta = {
        "format": "ra2vipas-channel-1",
        "receivers": names,
        "fit": fit,
        "sensitivity_dbm": int(min(int(r.rssi.min()) for r in recs)),
        "command": command,
    }
    return ChannelFile(meta=meta, rx_pos=rx_pos, rec_receiver=rec_receiver, rec_point=rec_point,
                       rec_start=np.asarray(start, dtype=np.int32), rec_seconds=np.asarray(secs, dtype=np.float32),
                       gap_ms=np.concatenate(gaps), rssi=np.concatenate(rssi))


def save(channel: ChannelFile, out: Path, extra_meta: dict | None = None) -> None:
    """Write ``channel`` to ``out`` atomically (a temporary file in the same folder, renamed)."""
    out = Path(out)
    meta = {**channel.meta, **(extra_meta or {})}
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".channel-", suffix=".npz", dir=out.parent)
    except OSError as err:
        raise ChannelFileError(f"cannot write {out}: {err.strerror or err}") from None
    try:
        with os.fdopen(fd, "wb") as handle:
            np.savez_compressed(handle, meta=np.asarray(json.dumps(meta, sort_keys=True)), rx_pos=channel.rx_pos,
                                rec_receiver=channel.rec_receiver, rec_point=channel.rec_point, rec_start=channel.rec_start,
                                rec_seconds=channel.rec_seconds, gap_ms=channel.gap_ms, rssi=channel.rssi)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # what open() would have given it (mkstemp makes it private)
        os.replace(tmp, out)
    except OSError as err:
        Path(tmp).unlink(missing_ok=True)
        raise ChannelFileError(f"cannot write {out}: {err.strerror or err}") from None


def load(path: Path) -> ChannelFile:
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            return ChannelFile(meta=meta, **{k: z[k] for k in ("rx_pos", "rec_receiver", "rec_point", "rec_start", "rec_seconds",
                                                                  "gap_ms", "rssi")})
    except (OSError, KeyError, ValueError) as err:
        raise ChannelFileError(f"cannot read the channel file {path}: {err}") from None


_CACHE: dict[str, ChannelFile] = {}


def find(name: str) -> Path:
    """The channel file ``name``: ``<name>.npz`` among the shipped ones, then in ``$RA2VIPAS_CHANNELS``."""
    folders = [DATA_DIR] + [Path(p) for p in os.environ.get(CHANNELS_ENV, "").split(os.pathsep) if p]
    for folder in folders:
        candidate = folder / f"{name}.npz"
        if candidate.is_file():
            return candidate
    raise ChannelFileError(f"no channel file {name!r} (looked in {', '.join(str(f) for f in folders)}; "
                           f"set {CHANNELS_ENV} to a folder of files written by `ra2vipas radio import`)")


def by_name(name: str) -> ChannelFile:
    """The channel file ``name`` (``find``), loaded once per process."""
    path = find(name)
    key = str(path)
    if key not in _CACHE:
        _CACHE[key] = load(path)
    return _CACHE[key]
