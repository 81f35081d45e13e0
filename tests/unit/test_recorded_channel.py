"""The recorded channel (issue 20): the importer of ``.mbd`` recordings (a small fixture, a
malformed one refused with its line number and nothing written), the shipped CC0 subset and its
credit, and the ``recorded`` radio drawing each receiver's packets from the recordings."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from ra2vipas.services.protocol.scenario import build_scenario
from ra2vipas.services.sensors import channel_file, physics
from ra2vipas.services.sensors.recorded import RecordedSchedule
from ra2vipas.services.sensors.world import GroundTruth, SimulatedPlatform, TrainingEpisode

RX_A, RX_B = "b827eb4521b4", "000000000101"
DEVICES = ('Dongles:{"%s": [[0.0, 0.0, 1.2], 1, "sensor10"], "%s": [[10.0, 0.0, 1.2], 2, "sensor11"]}\n'
           'Beacons:{"e78f135624ce": [[], 1, "beacon1"]}\n') % (RX_A, RX_B)


def _mbd(rx: str, start: float, rssi: list[int], gap: float = 0.455) -> str:
    return "".join(f"{start + k * gap:.9f},{rx},e78f135624ce,{v}\n" for k, v in enumerate(rssi))


@pytest.fixture()
def survey(tmp_path):
    """Two receivers, three beacon positions: a miniature of the dataset's hst/set_1."""
    folder = tmp_path / "set"
    folder.mkdir()
    (tmp_path / "tetam.dev").write_text(DEVICES)
    (folder / "sensor10_1.00_0.00_1.20.mbd").write_text(_mbd(RX_A, 1569304545.7, [-60, -61, -59, -62, -60, -58]))
    (folder / "sensor10_3.00_0.00_1.20.mbd").write_text(_mbd(RX_A, 1569304600.0, [-70, -72, -69, -71]))
    (folder / "sensor11_7.00_0.00_1.20.mbd").write_text(_mbd(RX_B, 1569304700.0, [-71, -73, -70]))
    return tmp_path, folder


def test_the_importer_reads_recordings_into_a_channel_file(survey):
    root, folder = survey
    out = root / "mini.npz"
    ch = channel_file.import_recordings(sorted(folder.glob("*.mbd")), root / "tetam.dev", out)
    loaded = channel_file.load(out)
    assert loaded.receivers == ["sensor10", "sensor11"] and len(loaded.rec_receiver) == 3
    assert loaded.rssi_of(0).tolist() == [-60, -61, -59, -62, -60, -58]
    assert np.allclose(loaded.times_s(0), [0.0, 0.455, 0.91, 1.365, 1.82, 2.275], atol=1e-3)
    assert np.allclose(loaded.distances_m(), [1.0, 3.0, 3.0], atol=1e-6)
    assert loaded.meta["sensitivity_dbm"] == -73 and loaded.meta["fit"] == ch.meta["fit"]
    trimmed = channel_file.import_recordings(sorted(folder.glob("*.mbd")), root / "tetam.dev", root / "t.npz", seconds=1.0,
                                             max_range_m=2.0, receivers=["sensor10"])
    assert len(trimmed.rec_receiver) == 1 and trimmed.rssi_of(0).tolist() == [-60, -61, -59]


@pytest.mark.parametrize("line, why", [
    ("1569304546.0,b827eb4521b4,e78f135624ce,-6x", "rssi"),
    ("1569304546.0,b827eb4521b4,e78f135624ce", "fields"),
    ("yesterday,b827eb4521b4,e78f135624ce,-60", "time"),
])
def test_a_malformed_line_is_refused_with_its_number_and_nothing_is_written(survey, line, why):
    root, folder = survey
    bad = folder / "sensor10_3.00_0.00_1.20.mbd"
    lines = bad.read_text().splitlines()
    lines.insert(2, line)
    bad.write_text("\n".join(lines) + "\n")
    out = root / "channel.npz"
    with pytest.raises(channel_file.ChannelFileError, match=r"sensor10_3.00_0.00_1.20.mbd:3: expected 'timestamp,receiver,beacon,rssi'"):
        channel_file.import_recordings(sorted(folder.glob("*.mbd")), root / "tetam.dev", out)
    assert not out.exists() and not list(root.glob(".channel-*"))
    proc = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "radio", "import", str(folder), "--devices", str(root / "tetam.dev"),
                           "-o", str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert ".mbd:3: expected" in proc.stderr and "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not out.exists()


def test_the_cli_writes_the_file_and_names_what_it_wrote(survey):
    root, folder = survey
    out = root / "ok.npz"
    proc = subprocess.run([sys.executable, "-m", "ra2vipas.cli.main", "radio", "import", str(folder), "--devices", str(root / "tetam.dev"),
                           "-o", str(out), "--licence", "CC0"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "3 recordings of 2 receivers, 13 packets" in proc.stdout
    meta = channel_file.load(out).meta
    assert meta["licence"] == "CC0" and meta["command"].startswith("ra2vipas radio import ")


def test_a_file_name_without_a_position_or_an_unknown_receiver_is_refused(survey):
    root, folder = survey
    (folder / "notes.mbd").write_text(_mbd(RX_A, 0.0, [-60]))
    with pytest.raises(channel_file.ChannelFileError, match="must be <receiver>_<x>_<y>_<z>.mbd"):
        channel_file.import_recordings(sorted(folder.glob("*.mbd")), root / "tetam.dev", root / "x.npz")
    with pytest.raises(channel_file.ChannelFileError, match="unknown receiver"):
        channel_file.import_recordings([], root / "tetam.dev", root / "x.npz", receivers=["sensor99"])


def test_the_shipped_subset_is_small_credited_and_found_without_a_download(monkeypatch):
    monkeypatch.delenv(channel_file.CHANNELS_ENV, raising=False)
    path = channel_file.find("cc0-tetam")
    assert path.stat().st_size < 300_000
    ch = channel_file.by_name("cc0-tetam")
    assert "CC0" in ch.meta["licence"] and "Dani" in ch.meta["source"]
    assert ch.meta["command"] == "ra2vipas radio import hst/set_1 --devices cnf/tetam.dev --seconds 120 --max-range 9 -o cc0-tetam.npz"
    assert (path.parent / "LICENSE-cc0-tetam.txt").read_text().startswith("Creative Commons Legal Code\n\nCC0 1.0 Universal")
    assert "ra2vipas radio import hst/set_1" in (path.parent / "README.md").read_text()
    assert len(ch.receivers) == 12 and ch.distances_m().max() <= 9.0
    with pytest.raises(channel_file.ChannelFileError, match="no channel file 'nowhere'"):
        channel_file.find("nowhere")


def test_a_user_channel_is_found_in_the_channels_folders(survey, monkeypatch):
    root, folder = survey
    channel_file.import_recordings(sorted(folder.glob("*.mbd")), root / "tetam.dev", root / "lab.npz")
    monkeypatch.setenv(channel_file.CHANNELS_ENV, str(root))
    assert channel_file.find("lab") == root / "lab.npz"


def test_recorded_packets_come_from_recordings_at_the_matching_distance():
    sc = build_scenario("ble-recorded")
    ch = channel_file.by_name(sc.radio_channel)
    dist = ch.distances_m()
    for d in (1.5, 3.0, 5.0):
        path = np.tile([[d, 0.0]], (sc.steps, 1))
        s = RecordedSchedule(sc, np.random.default_rng(int(d * 10)), path)
        assert s.rx[0] != s.rx[1]  # Rx(dir) hears a recording of its own
        for r in range(2):
            chosen = s.recording[r]
            assert np.all(np.abs(dist[chosen] - d) < 1.0) and np.all(ch.rec_receiver[chosen] == s.rx[r])
        packets = [s.packets(t, (-60.0, -60.0)) for t in range(sc.steps)]
        iso = [a for p in packets for a in p if a.receiver == "iso"]
        recorded = set(ch.rssi_of(int(s.recording[0, 0])).tolist())
        assert iso and all(a.rssi_dbm in recorded for a in iso)  # real values, unchanged
        rate = len(iso) / (sc.steps * sc.rf_period_s)
        assert 1.0 < rate < 3.0  # the dataset's ~2 packets per second
        assert all(0.0 <= a.offset_s < sc.rf_period_s for p in packets for a in p)
        assert sum(1 for p in packets if not p) > sc.steps // 2  # most steps carry nothing


def test_rx_dir_adds_the_antennas_gain_to_its_recording():
    sc = build_scenario("ble-recorded")
    path = np.tile([[3.0, 0.0]], (sc.steps, 1))
    level = float(physics.path_loss_dbm(sc, 3.0))
    aligned = RecordedSchedule(sc, np.random.default_rng(5), path)
    away = RecordedSchedule(sc, np.random.default_rng(5), path)
    a = [x.rssi_dbm for t in range(sc.steps) for x in aligned.packets(t, (level, level)) if x.receiver == "dir"]
    b = [x.rssi_dbm for t in range(sc.steps) for x in away.packets(t, (level, level - 6.4)) if x.receiver == "dir"]
    assert a and len(b) <= len(a) and b == [v - 6.0 for v in a][:len(b)]  # the gain, in whole dB; a packet pushed below the floor is lost


def test_a_walking_tx_changes_recordings_and_the_preset_runs_from_a_fresh_clone():
    sc = build_scenario("ble-recorded", {"n_targets": 2})
    walk = GroundTruth(positions_m=np.array([[1.5, 0.0], [0.0, 5.0]]), tx_index=0, walkers=np.array([0]),
                       walker_positions_m=np.linspace([1.5, 0.0], [6.0, 0.0], sc.steps)[:, None, :])
    w = SimulatedPlatform(sc, 1, 0, layout=walk)
    assert len(set(w._packets.recording[0].tolist())) > 3
    ms = [w.sense(t, 0.0) for t in range(sc.steps)]
    assert all(m.rf is None for m in ms) and sum(len(m.adverts) for m in ms) > 20
    near = [a.rssi_dbm for m in ms[:30] for a in m.advertisements("iso")]
    far = [a.rssi_dbm for m in ms[-30:] for a in m.advertisements("iso")]
    assert np.mean(near) > np.mean(far)  # the real building's path loss
    samples = list(TrainingEpisode(build_scenario("ble-recorded", {"n_train": 200}), 1).samples())
    assert sum(len(s.adverts) for s in samples) > 20 and all(s.iso_rssi_dbm is None for s in samples)
