"""The reference hardware node of examples/hardware_node with BLE receivers (protocol 1.3
adverts) on the fake scanner backend: a fake tag advertises every 0.45 s plus advDelay and each
receiver hears ~90 % of the packets, whole-dBm RSSI from the fake driver's model. The node is
the example's own ``main`` with ``--ble-tag``; only the scanner factory is the fake one. With
``--ble-tag`` given more than once (protocol 1.4, several tags), tag k is carried by target
(tx + k) mod N of the fake layout and advertises on its own schedule.

    python ble_node.py --rig ble-1 --connect tcp/ROUTER:7447 [--ble-tag A --ble-tag B] [--all-tags | --first-tag-only] [--pair-training]
                       [--slow-tag SECONDS]

``--all-tags``, ``--first-tag-only`` and ``--pair-training`` are bugs for the conformance kit's tests: the
node sends every tag it listens for, or tag 0's only, whatever the episode's ``n_tags``; its training stream
is made-up RSSI pairs. A tag given as ``ibeacon:UUID:MAJOR:MINOR`` advertises that identity from an address that changes every
2 s (a resolvable private address). ``--slow-tag SECONDS`` is no bug: tags 1 and up are battery beacons that advertise every
SECONDS, the first time SECONDS after an episode starts listening for them (an unlucky phase).
"""

import importlib.util
import math
import random
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[2] / "examples" / "hardware_node"
sys.path.insert(0, str(HERE))
import ble_receiver  # noqa: E402  (the example's module, found beside hardware_node.py)

spec = importlib.util.spec_from_file_location("hardware_node", HERE / "hardware_node.py")
example = importlib.util.module_from_spec(spec)
sys.modules["hardware_node"] = example
spec.loader.exec_module(example)

TAG = "e7:8f:13:56:24:ce"


SLOW_TAG_S = 0.0  # --slow-tag: tags 1 and up advertise this rarely (0: every 0.45 s, as tag 0)
LISTENING_SINCE: dict[int, float] = {}  # tag -> when the current episode's receivers began listening for it


class FakeTag:
    """Plays a tag's advertisements into the fake scanners, RSSI from the driver's geometry: tag k
    (address ``address``) is carried by target (tx + k) mod N."""

    def __init__(self, driver, address: str = TAG, k: int = 0) -> None:
        self.driver, self.address, self.k = driver, address, k
        self.rng = random.Random(7 + k)
        self.stop = threading.Event()
        threading.Thread(target=self.run, daemon=True).start()

    def _silent(self) -> bool:
        """A slow beacon (``--slow-tag``, tags 1 and up) between its advertisements, or not listened for."""
        if not SLOW_TAG_S or self.k == 0:
            return False
        since = LISTENING_SINCE.get(self.k)
        if since is None:
            return True
        elapsed = time.monotonic() - since
        return elapsed < SLOW_TAG_S or (elapsed % SLOW_TAG_S) > 0.5

    def run(self) -> None:
        while not self.stop.wait(0.45 + self.rng.uniform(0.0, 0.01)):
            if self._silent():
                continue
            d = self.driver
            carrier = (d.tx + self.k) % len(d.bearings)
            training = d.training_range_m if self.k == 0 else None  # a training episode: tag 0 on the optical axis
            g = -30.0 - 20.0 * math.log10(d.ranges[carrier] if training is None else training)
            delta = 0.0 if training is not None else example.wrap(d.pan - d.bearings[carrier])
            gain = 10.0 * math.log10(max(1.0 - 0.5 * delta * delta, 0.01))
            sender, payload = self.address, None
            if self.address.startswith("ibeacon:"):  # a beacon named by its identity: its address rotates every 2 s
                payload = ble_receiver.ibeacon_data(self.address)
                turn = int(time.monotonic() / 2.0)
                sender = f"4{self.k}:{turn % 256:02X}:{turn // 256 % 256:02X}:00:00:0{self.k}"
            for scanner, level in zip(list(ble_receiver.FakeScanner.instances), (g, g + gain)):
                if self.rng.random() > 0.1:
                    scanner.emit(sender, round(level + self.rng.gauss(0.0, 3.0)), manufacturer_data=payload)


original = ble_receiver.BleReceivers.__init__


def fake_backend(self, tag, adapters=None, scanner_factory=None, clock=time.monotonic):
    original(self, tag, adapters, scanner_factory=ble_receiver.FakeScanner, clock=clock)


ble_receiver.BleReceivers.__init__ = fake_backend
real_with_ble = ble_receiver.with_ble


def with_ble_and_tag(driver, receivers):
    driver.tx_indices = [(driver.tx + k) % len(driver.bearings) for k in range(len(receivers.tags))]  # for --publish-truth
    for k, address in enumerate(receivers.tags):
        FakeTag(driver, address, k)
    return real_with_ble(driver, receivers)


ble_receiver.with_ble = with_ble_and_tag

if __name__ == "__main__":
    if "--all-tags" in sys.argv:  # a bug for the conformance kit's tests: every tag listened for, whatever the episode's n_tags
        sys.argv.remove("--all-tags")
        real_reset = ble_receiver.BleReceivers.reset
        ble_receiver.BleReceivers.reset = lambda self, n_tags=None: real_reset(self, None)
    if "--first-tag-only" in sys.argv:  # a bug for the kit's tests: only tag 0 listened for, whatever the episode's n_tags
        sys.argv.remove("--first-tag-only")
        real_reset = ble_receiver.BleReceivers.reset
        ble_receiver.BleReceivers.reset = lambda self, n_tags=None: real_reset(self, 1)
    if "--pair-training" in sys.argv:  # a bug for the kit's tests: the fake driver's made-up RSSI pairs as the training stream
        sys.argv.remove("--pair-training")

        def pair_training(self, n, lo, hi, rng, d):
            return [{"index": j, "iso_rssi_dbm": self.driver.training_sample(d, self.nu)[0], "frames": [{"box_bearings_rad": []}] * self.nu}
                    for j in range(n)]

        example.HardwareNode.train_on_adverts = pair_training
    if "--slow-tag" in sys.argv:
        at = sys.argv.index("--slow-tag")
        SLOW_TAG_S = float(sys.argv[at + 1])
        del sys.argv[at:at + 2]
        listening_reset = ble_receiver.BleReceivers.reset

        def reset_and_note(self, n_tags=None):
            listening_reset(self, n_tags)
            wanted = len(self.tags) if n_tags is None else int(n_tags)
            LISTENING_SINCE.clear()
            LISTENING_SINCE.update({k: time.monotonic() for k in range(1, wanted)})

        ble_receiver.BleReceivers.reset = reset_and_note
    if "--ble-tag" not in sys.argv:
        sys.argv += ["--ble-tag", TAG]
    example.main()
