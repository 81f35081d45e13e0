#!/usr/bin/env python3
"""A reference ra2vipas sensors node for real hardware: zenoh + numpy + the standard library.

It imports nothing from ra2vipas. It speaks the wire protocol of docs/protocol.md (v1 with the
rig descriptor) and drives a *driver* object: ``FakeDriver`` below simulates a pan unit, a
camera with an object detector and two BLE receivers well enough to run campaigns. A hardware
team replaces it with theirs (same four methods) and edits ``DESCRIPTOR``.

    python hardware_node.py --rig cam-1 --connect tcp/ROUTER:7447 [--user U --password-file F]

What it does, in the protocol's terms:

* serves its descriptor on ``ra2vipas/v1/rig/{rig}/info``;
* ``ra2vipas/v1/control/{rig}/episode``: ``EpisodeStart`` (kind "start") readies an episode,
  ``EpisodeStop`` (kind "stop") drops it;
* ``ra2vipas/v1/data/{rig}/command``: ``Command(step, pan_rad)``: in *fast* mode it moves, senses
  and answers with ``Measurement(step)`` at once (a repeated command gets the same sample again,
  a command for another step is dropped); in *realtime* mode sample 0 is taken when Command(0)
  arrives, sample k at t0 + k T_RF at the last commanded pan, and ``EpisodeTiming`` follows the
  last sample by one period;
* ``ra2vipas/v1/data/{rig}/training``: records ``n_train`` samples of the Tx alone in view;
* declares ``ra2vipas/v1/alive/sensors/{rig}`` last.
* With ``--publish-truth`` (the fake driver knows its layout, as a survey does) it also puts
  ``EpisodeTruth`` on ``ra2vipas/v1/truth/{rig}/episode``: a real rig leaves that to an operator.
"""

from __future__ import annotations

import argparse
import heapq
import json
import logging
import math
import signal
import threading
import time

import numpy as np
import zenoh

PREFIX = "ra2vipas/v1"
log = logging.getLogger("hardware-node")

# What this platform is: edit for your hardware (docs/protocol.md, "The rig descriptor").
DESCRIPTOR = {
    "kind": "hardware",
    "vendor": "Example Lab",
    "model": "fake pan unit + fake BLE pair",
    "frames_per_rf": 10,  # nu: camera frames per RF sample
    "rf_period_s": 0.1,  # T_RF
    "fov_half_angle_deg": 22.5,
    "box_bearing_noise_deg": 0.25,
    "rx_dir": {"model": "unknown"},  # nobody measured the antenna: the controller learns the lobe
    "modes": ["fast", "realtime"],
    "training": True,
    "episode_truth": False,  # set by --publish-truth
    "training_truth": False,
    "protocol": "1.1",  # the protocol version this node speaks (docs/protocol.md, "Compatibility")
}


def wrap(angle: float) -> float:
    """An angle in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


class FakeDriver:
    """The hardware. Replace with yours: ``move_to``, ``capture``, ``read_rssi``, ``training_sample``.

    The fake: ``n_targets`` people at fixed places (seeded), one carrying the Tx; a dB-gain
    directional antenna; detections Bernoulli with a POD falling with range; 3 dB RSSI noise.
    """

    def __init__(self, seed: int = 0, n_targets: int = 8, fov_half_angle_deg: float = 22.5, box_noise_deg: float = 0.25) -> None:
        self.rng = np.random.default_rng(seed)
        self.fov = math.radians(fov_half_angle_deg)
        self.box_noise = math.radians(box_noise_deg)
        self.layout(seed, n_targets)
        self.pan = 0.0

    def layout(self, seed: int, n_targets: int) -> None:
        """Place the people (a real rig: whoever stands there)."""
        rng = np.random.default_rng(seed)
        self.bearings = rng.uniform(-math.pi, math.pi, n_targets)
        self.ranges = rng.uniform(1.0, 5.0, n_targets)
        self.tx = int(rng.integers(n_targets))
        self.ranges[self.tx] = rng.uniform(1.0, 3.5)

    training_range_m: float | None = None  # while a training episode records: where the Tx is (on the optical axis)

    def end_training(self) -> None:
        self.training_range_m = None

    def move_to(self, pan_rad: float) -> float:
        """Drive the pan unit; return the pan actually reached [rad], wrapped."""
        self.pan = wrap(pan_rad)
        return self.pan

    @staticmethod
    def _pod(d):
        return 1.0 / ((1.0 + np.exp(4.0 * (d - 4.5))) * (1.0 + np.exp(-(d - 2.5))))

    def capture(self, frames: int) -> list[list[float]]:
        """``frames`` camera frames: per frame, the detector's box bearings relative to the optical
        axis [rad], sorted ascending (no identities)."""
        rel = (self.bearings - self.pan + math.pi) % (2.0 * math.pi) - math.pi
        seen = np.abs(rel) <= self.fov
        out = []
        for _ in range(frames):
            hit = seen & (self.rng.random(rel.size) < self._pod(self.ranges))
            boxes = rel[hit] + self.rng.normal(0.0, self.box_noise, int(hit.sum()))
            out.append(sorted(float(b) for b in boxes))
        return out

    def read_rssi(self) -> tuple[float, float]:
        """One RSSI sample of Rx(iso) and Rx(dir) [dBm]."""
        g = -30.0 - 20.0 * math.log10(self.ranges[self.tx])
        delta = wrap(self.pan - self.bearings[self.tx])
        gain = 10.0 * math.log10(max(1.0 - 0.5 * delta * delta, 0.01))
        return float(g + self.rng.normal(0, 3.0)), float(g + gain + self.rng.normal(0, 3.0))

    def training_sample(self, range_m: float, frames: int) -> tuple[float, list[list[float]]]:
        """The Tx alone in view at ``range_m`` on the optical axis: iso RSSI and frames. (With BLE
        receivers only the frames are used: the RSSI is what they hear; ``training_range_m`` tells a
        simulated tag where the Tx is until ``end_training``.)"""
        self.training_range_m = range_m
        g = -30.0 - 20.0 * math.log10(range_m)
        hits = self.rng.random(frames) < self._pod(range_m)
        return float(g + self.rng.normal(0, 3.0)), [[float(self.rng.normal(0.0, self.box_noise))] if h else [] for h in hits]


class Episode:
    def __init__(self, start: dict) -> None:
        self.start = start
        self.id = start["episode_id"]
        self.steps = int(start["scenario"]["steps"])
        self.realtime = start.get("mode") == "realtime"
        self.last: bytes | None = None  # fast: the last measurement sent
        self.last_step = -1
        self.pan = 0.0
        self.t0: float | None = None
        self.next_step = 0
        self.sent_at: dict[int, float] = {}
        self.latencies: list[float] = []
        self.late = 0


class HardwareNode:
    def __init__(self, session: zenoh.Session, rig: str, driver: FakeDriver, publish_truth: bool = False) -> None:
        self.session, self.rig, self.driver = session, rig, driver
        self.publish_truth = publish_truth
        self.descriptor = dict(DESCRIPTOR, rig=rig, episode_truth=publish_truth)
        self.n_tags = int(getattr(driver, "n_tags", 1))  # tags its receivers listen for (ble_receiver.py)
        if hasattr(driver, "read_adverts"):  # a BLE receiver (ble_receiver.py): adverts need protocol 1.3
            self.descriptor.update(protocol="1.3", radio="adverts")
            if self.n_tags > 1:  # several tags need 1.4; saying how many (``tags``) 1.5, so a campaign asking more is refused
                self.descriptor.update(protocol="1.5", tags=self.n_tags)
        self.nu = int(self.descriptor["frames_per_rf"])
        self.period = float(self.descriptor["rf_period_s"])
        self.lock = threading.RLock()  # one driver, one episode table
        self.episodes: dict[str, Episode] = {}
        self.finished: dict[str, None] = {}
        self.early: dict[str, bytes] = {}  # a Command(0) that overtook its EpisodeStart
        self.timers: list = []
        self.cv = threading.Condition(self.lock)
        self.closing = False
        key = f"{PREFIX}/{{}}/{rig}/{{}}"
        self.pub_measurement = session.declare_publisher(key.format("data", "measurement"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self.pub_timing = session.declare_publisher(key.format("result", "timing"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self.pub_truth = session.declare_publisher(key.format("truth", "episode"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self.declared = [
            session.declare_subscriber(key.format("control", "episode"), self.on_control),
            session.declare_subscriber(key.format("data", "command"), self.on_command),
            session.declare_queryable(key.format("data", "training"), self.on_training),
            session.declare_queryable(key.format("rig", "info"), self.on_info),
        ]
        self.declared.append(session.liveliness().declare_token(f"{PREFIX}/alive/sensors/{rig}"))  # last: everything is in place
        self.timer_thread = threading.Thread(target=self.run_timers, daemon=True)
        self.timer_thread.start()

    # -- helpers ---------------------------------------------------------------------------
    @staticmethod
    def parse(sample) -> dict | None:
        try:
            payload = sample.payload.to_bytes()
            if len(payload) > 1 << 20:
                return None
            msg = json.loads(payload)
            return msg if isinstance(msg, dict) else None
        except (ValueError, UnicodeDecodeError):
            return None

    def measure(self, ep: Episode, step: int, pan: float) -> bytes:
        reached = self.driver.move_to(pan)
        frames = self.driver.capture(self.nu)
        message = {"episode_id": ep.id, "step": step, "pan_rad": reached, "frames": [{"box_bearings_rad": f} for f in frames]}
        if hasattr(self.driver, "read_adverts"):  # protocol 1.3: what each receiver heard since the last step, maybe nothing
            adverts = self.driver.read_adverts()
            if adverts:
                message["adverts"] = adverts
        else:
            iso, direct = self.driver.read_rssi()
            message["rf"] = {"iso_rssi_dbm": iso, "dir_rssi_dbm": direct}
        return json.dumps(message).encode()

    # -- control -------------------------------------------------------------------------------
    def on_control(self, sample) -> None:
        msg = self.parse(sample)
        if msg is None or not isinstance(msg.get("episode_id"), str):
            log.warning("malformed control message dropped")
            return
        with self.lock:
            if msg.get("kind") == "stop":
                self.end(msg["episode_id"])
                return
            if msg.get("kind") != "start" or msg["episode_id"] in self.episodes:
                return
            try:
                ep = Episode(msg)
            except (KeyError, TypeError, ValueError):
                log.warning("malformed EpisodeStart dropped")
                return
            if ep.steps < 1 or ep.steps > 10000:
                return
            self.episodes[ep.id] = ep
            self.finished.pop(ep.id, None)
            try:
                wanted = max(int(msg["scenario"].get("n_tags", 1)), 1)  # the tags the campaign searches for
            except (AttributeError, TypeError, ValueError):
                wanted = 1
            if hasattr(self.driver, "reset_adverts"):  # the first step's adverts are those heard from now on
                if wanted > self.n_tags > 1:
                    log.warning("episode %s searches for %d tags; this node listens for %d: tags %d.. are never heard",
                                ep.id, wanted, self.n_tags, self.n_tags)
                self.listen_for(wanted)
            if self.publish_truth:
                d = self.driver
                truth = {"episode_id": ep.id, "bearings_rad": [round(float(b), 6) for b in d.bearings],
                         "ranges_m": [round(float(r), 4) for r in d.ranges], "tx_index": d.tx}
                carriers = getattr(d, "tx_indices", None)  # several tags (1.4): who carries tag k, k < the campaign's n_tags
                if wanted > 1 and carriers:
                    truth["tx_indices"] = [int(c) for c in carriers[:wanted]]
                    if getattr(d, "tag_addresses", None):
                        truth["tag_addresses"] = list(d.tag_addresses[:wanted])
                self.pub_truth.put(json.dumps(truth).encode())
            early = self.early.pop(ep.id, None)
            if early is not None:
                self.handle_command(json.loads(early))

    def end(self, episode_id: str) -> None:
        self.early.pop(episode_id, None)
        if self.episodes.pop(episode_id, None) is not None:
            for k, tag in getattr(self.driver, "silent_tags", lambda: [])():  # BLE receivers: say so once, at the end
                log.warning("episode %s: tag %d (%s) was never heard: out of range, not advertising, or its address changed "
                            "(name a beacon whose address rotates by its identity, --ble-tag ibeacon:UUID:MAJOR:MINOR)",
                            episode_id, k, tag)
            self.finished[episode_id] = None
            while len(self.finished) > 10000:
                self.finished.pop(next(iter(self.finished)))

    # -- commands ------------------------------------------------------------------------------
    def on_command(self, sample) -> None:
        msg = self.parse(sample)
        if msg is None or not isinstance(msg.get("episode_id"), str) or not isinstance(msg.get("step"), int) \
                or not isinstance(msg.get("pan_rad"), (int, float)) or not -7.0 <= msg["pan_rad"] <= 7.0:
            log.warning("malformed command dropped")
            return
        with self.lock:
            if msg["episode_id"] not in self.episodes:
                if msg["step"] == 0 and msg["episode_id"] not in self.finished:
                    self.early[msg["episode_id"]] = json.dumps(msg).encode()
                    while len(self.early) > 1000:
                        self.early.pop(next(iter(self.early)))
                return
            self.handle_command(msg)

    def handle_command(self, msg: dict) -> None:
        ep = self.episodes[msg["episode_id"]]
        step, pan = msg["step"], wrap(float(msg["pan_rad"]))
        if ep.realtime:
            now = time.monotonic()
            ep.pan = pan
            if ep.t0 is None:
                if step == 0:
                    ep.t0 = now
                    self.tick(ep.id, 0)
                return
            sent = ep.sent_at.pop(step - 1, None)
            if sent is not None:
                ep.latencies.append((now - sent) * 1e3)
                if step < ep.next_step:
                    ep.late += 1
            return
        if step == ep.last_step and ep.last is not None:
            self.pub_measurement.put(ep.last)  # a repeated command: the same sample again
            return
        if step != ep.last_step + 1 or step >= ep.steps:
            return
        ep.last, ep.last_step = self.measure(ep, step, pan), step
        self.pub_measurement.put(ep.last)
        if step == ep.steps - 1:
            self.end(ep.id)

    # -- realtime ------------------------------------------------------------------------------
    def tick(self, episode_id: str, step: int) -> None:
        ep = self.episodes.get(episode_id)
        if ep is None or step != ep.next_step:
            return
        if step >= ep.steps:  # one period after the last sample: the timing report
            self.pub_timing.put(json.dumps({"episode_id": ep.id, "latencies_ms": [round(v, 4) for v in ep.latencies],
                                            "late_commands": ep.late}).encode())
            self.end(ep.id)
            return
        self.pub_measurement.put(self.measure(ep, step, ep.pan))
        ep.sent_at[step] = time.monotonic()
        ep.next_step = step + 1
        self.schedule(ep.t0 + ep.next_step * self.period, ep.id, ep.next_step)  # the grid: catch up, never slip

    def schedule(self, when: float, episode_id: str, step: int) -> None:
        heapq.heappush(self.timers, (when, episode_id, step))
        self.cv.notify()

    def run_timers(self) -> None:
        with self.cv:
            while not self.closing:
                if not self.timers or self.timers[0][0] > time.monotonic():
                    self.cv.wait(None if not self.timers else max(0.0, self.timers[0][0] - time.monotonic()))
                    continue
                _, episode_id, step = heapq.heappop(self.timers)
                self.tick(episode_id, step)

    # -- queryables ----------------------------------------------------------------------------
    def on_info(self, query) -> None:
        query.reply(query.key_expr, json.dumps(self.descriptor).encode(), encoding=zenoh.Encoding.APPLICATION_JSON)

    def on_training(self, query) -> None:
        threading.Thread(target=self.train, args=(query,), daemon=True).start()  # never block Zenoh's thread

    def train(self, query) -> None:
        try:
            req = json.loads(query.payload.to_bytes()) if query.payload is not None else None
            job, sc = req["job_id"], req["scenario"]
            n, lo, hi = int(sc["n_train"]), float(sc["train_min_range_m"]), float(sc["train_max_range_m"])
        except (ValueError, KeyError, TypeError):
            query.reply_err(b"malformed TrainingRequest", encoding=zenoh.Encoding.TEXT_PLAIN)
            return
        # a real rig: ask someone to walk the Tx along the optical axis between lo and hi while recording
        rng = np.random.default_rng(0)
        d, samples = rng.uniform(lo, hi), []
        if hasattr(self.driver, "read_adverts"):
            samples = self.train_on_adverts(n, lo, hi, rng, d)
        else:
            with self.lock:
                for j in range(n):
                    iso, frames = self.driver.training_sample(d, self.nu)
                    samples.append({"index": j, "iso_rssi_dbm": iso, "frames": [{"box_bearings_rad": f} for f in frames]})
                    d = min(max(d + rng.normal(0.0, 0.2), lo), hi)
        query.reply(query.key_expr, json.dumps({"job_id": job, "samples": samples}).encode(), encoding=zenoh.Encoding.APPLICATION_JSON)

    def listen_for(self, n_tags: int) -> None:
        """BLE receivers: forget what was heard; from now on take tags 0 .. n_tags - 1 (the campaign's, its
        scenario's n_tags, docs/tags.md). A one-tag driver's ``reset_adverts`` takes no argument."""
        if self.n_tags > 1:
            self.driver.reset_adverts(n_tags)
        else:
            self.driver.reset_adverts()

    def train_on_adverts(self, n: int, lo: float, hi: float, rng, d: float) -> list[dict]:
        """BLE receivers (protocol 1.3): training takes real time. Each sample is one T_RF of what Rx(iso)
        heard of tag 0 (the rig's POD model is learned from tag 0, docs/tags.md), possibly nothing, and
        the camera's nu frames of the Tx on the optical axis (``training_sample``'s frames; its RSSI, a
        pair, is not used). n_train samples take n_train x T_RF."""
        self.listen_for(1)
        samples: list[dict] = []
        t0 = time.monotonic()
        for j in range(n):
            with self.lock:  # per sample: the Zenoh threads are never held for the whole recording
                _, frames = self.driver.training_sample(d, self.nu)
            time.sleep(max(0.0, t0 + (j + 1) * self.period - time.monotonic()))
            heard = [a for a in self.driver.read_adverts() if a["receiver"] == "iso" and a.get("tag", 0) == 0]
            samples.append({"index": j, "adverts": heard, "frames": [{"box_bearings_rad": f} for f in frames]})
            d = min(max(d + rng.normal(0.0, 0.2), lo), hi)
        if hasattr(self.driver, "end_training"):
            self.driver.end_training()
        return samples

    def close(self) -> None:
        with self.cv:
            self.closing = True
            self.cv.notify()
        for obj in reversed(self.declared):
            try:
                obj.undeclare()
            except Exception:
                pass


def main(node_class: type = HardwareNode, driver_class: type = FakeDriver) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rig", default="cam-1")
    parser.add_argument("--connect", action="append", default=[], help="Zenoh endpoint of the router, e.g. tcp/10.0.0.2:7447")
    parser.add_argument("--user", help="Zenoh user name (a secured deployment)")
    parser.add_argument("--password-file", help="file holding the Zenoh password")
    parser.add_argument("--seed", type=int, default=0, help="the fake driver's layout")
    parser.add_argument("--publish-truth", action="store_true", help="publish EpisodeTruth (the fake driver knows its layout)")
    parser.add_argument("--ble-tag", metavar="TAG", action="append", default=[],
                        help="real BLE receivers (bleak): the Tx tag's address, e.g. E7:8F:13:56:24:CE, or for a beacon whose "
                             "address changes the identity it advertises, ibeacon:UUID[:MAJOR[:MINOR]] or "
                             "eddystone:NAMESPACE[:INSTANCE]; repeat it for several tags (tag k is the k-th given; protocol "
                             "1.4); the fake driver keeps the pan unit and the camera (ble_receiver.py, README)")
    parser.add_argument("--iso-adapter", default="hci0", help="the BlueZ adapter of Rx(iso) (with --ble-tag)")
    parser.add_argument("--dir-adapter", default="hci1", help="the BlueZ adapter of Rx(dir), the directional one (with --ble-tag)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client" if args.connect else "peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    else:
        conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    if args.user:
        password = open(args.password_file).read().strip() if args.password_file else ""
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(args.user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    driver = driver_class(args.seed, fov_half_angle_deg=DESCRIPTOR["fov_half_angle_deg"], box_noise_deg=DESCRIPTOR["box_bearing_noise_deg"])
    receivers = None
    if args.ble_tag:
        from ble_receiver import BleReceivers, ScannerError, with_ble

        try:
            receivers = BleReceivers(args.ble_tag, {"iso": args.iso_adapter, "dir": args.dir_adapter})
        except ValueError as err:
            parser.error(f"--ble-tag: {err}")  # one line, exit 2
        try:
            receivers.start()
        except ScannerError as err:
            log.error("%s", err)
            raise SystemExit(1) from None
        driver = with_ble(driver, receivers)
    try:
        with zenoh.open(conf) as session:
            node = node_class(session, args.rig, driver, args.publish_truth)
            log.info("hardware node %s up", args.rig)
            stop.wait()
            node.close()
    finally:
        if receivers is not None:
            receivers.stop()
    log.info("hardware node %s stopped", args.rig)


if __name__ == "__main__":
    main()
