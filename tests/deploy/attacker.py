"""A hostile node with a rig's credentials: ``python -m tests.deploy.attacker REPORT.json``, its
Zenoh identity from the environment (``RA2VIPAS_ZENOH_*``, e.g. a ``security init`` env file).

Until SIGTERM/SIGINT it keeps trying what issue 14's probes did: it eavesdrops on every rig's
control plane and data to learn episode ids; it announces a fake rig ``evil`` (sensors and
controller), a second ``rig-2``, a learner and an orchestrator; for every episode it hears of
it forges the result and the truth on that rig's keys (every estimate and the Tx at bearing
0.5 rad: a DR of 1) and then stops the episode; and it keeps forging results, truth and
stops on rig-2's keys for guessed ids. On exit it writes what it heard and sent to REPORT.
"""

from __future__ import annotations

import json
import sys
import threading
import time

import zenoh

from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import EpisodeResult, EpisodeStop, EpisodeTruth, dump, episode_control_adapter
from ra2vipas.services.transport.runtime import wait_for_shutdown_signal
from ra2vipas.services.transport.zenoh_config import ZenohSettings

FAKE_TOKENS = [("sensors", "evil"), ("controller", "evil"), ("sensors", "rig-2"), ("controller", "rig-2"),
               ("learner", "evil"), ("orchestrator", "evil")]
BEARING = 0.5


class Attacker:
    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.lock = threading.Lock()
        self.sent: set[bytes] = set()
        self.report = {"heard": 0, "heard_starts": 0, "forged": 0, "attempts": 0, "heard_keys": []}
        self.declared = [session.liveliness().declare_token(keys.alive(role, name)) for role, name in FAKE_TOKENS]
        for pattern in (f"{keys.PREFIX}/control/**", f"{keys.PREFIX}/data/rig-2/**", f"{keys.PREFIX}/result/**", f"{keys.PREFIX}/truth/**"):
            self.declared.append(session.declare_subscriber(pattern, self._on_sample))
        self.declared.append(session.declare_queryable(keys.training("rig-2"), lambda q: q.reply(keys.training("rig-2"), b"{}")))

    def _put(self, key: str, payload: bytes) -> None:
        with self.lock:
            self.sent.add(payload)
            self.report["attempts"] += 1
        self.session.put(key, payload)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        with self.lock:
            if payload in self.sent:  # its own forgeries, delivered locally
                return
            self.report["heard"] += 1
            if len(self.report["heard_keys"]) < 20:
                self.report["heard_keys"].append(str(sample.key_expr))
        rig = keys.rig_of(str(sample.key_expr))
        if rig is None or "/control/" not in str(sample.key_expr):
            return
        try:
            start = episode_control_adapter.validate_json(payload)
        except ValueError:
            return
        if start.kind != "start":
            return
        with self.lock:
            self.report["heard_starts"] += 1
        self.forge(rig, start.episode_id, start.scenario.steps)

    def forge(self, rig: str, episode_id: str, steps: int) -> None:
        result = EpisodeResult(episode_id=episode_id, rig=rig, estimates_rad=(BEARING,) * steps, pans_rad=(BEARING,) * steps,
                               rewards=(1.0,) * steps)
        truth = EpisodeTruth(episode_id=episode_id, bearings_rad=(BEARING,), ranges_m=(2.0,), tx_index=0)
        self._put(keys.episode_result(rig), dump(result))
        self._put(keys.episode_truth(rig), dump(truth))
        self._put(keys.episode_control(rig), dump(EpisodeStop(episode_id=episode_id, reason="forged")))
        with self.lock:
            self.report["forged"] += 1

    def guess(self, n: int) -> None:
        """Ids in the shape `campaign.test.algorithm.attempt`, for campaigns it cannot see."""
        for algorithm in ("ra2vipas", "rapas"):
            self.forge("rig-2", f"guess{n % 7}.{n % 3}.{algorithm}.1", 30)

    def close(self) -> None:
        for d in reversed(self.declared):
            try:
                d.undeclare()
            except Exception:
                pass


def main(report_path: str) -> None:
    settings = ZenohSettings.from_sources()
    with zenoh.open(settings.to_zenoh()) as session:
        attacker = Attacker(session)
        stop = threading.Event()

        def keep_guessing() -> None:
            n = 0
            while not stop.wait(0.2):
                attacker.guess(n)
                n += 1

        worker = threading.Thread(target=keep_guessing, daemon=True)
        worker.start()
        print("attacker up", flush=True)
        try:
            wait_for_shutdown_signal()
        finally:
            stop.set()
            worker.join(5)
            attacker.close()
            with open(report_path, "w") as f:
                json.dump(attacker.report, f)
    time.sleep(0.1)


if __name__ == "__main__":
    main(sys.argv[1])
