"""Deliberately broken controllers for the controller conformance kit's tests: our
``ControllerNode`` with one bug each, chosen by the first argument.

    python broken_controller.py ignores-stop --rig bad-c1 --connect tcp/ROUTER:7447
    python broken_controller.py step-t --rig bad-c2 --connect tcp/ROUTER:7447

* ``ignores-stop``: it keeps commanding the episodes it was told to stop;
* ``step-t``: it answers Measurement(t) with a Command of step t instead of t + 1;
* ``token-first``: it declares its liveliness token before anything else, then takes
  ``SETUP_S`` to declare its subscriptions and queryable;
* ``v1-0`` (not broken: old): it serves no ``rig/{rig}/policies`` and reports no rejection,
  as a 1.0 controller; the kit skips those two optional rules.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from ra2vipas.services.controller.node import ControllerNode
from ra2vipas.services.protocol import keys
from ra2vipas.services.protocol.messages import EpisodeStop, decode, episode_control_adapter


class IgnoresStop(ControllerNode):
    def _on_control(self, payload: bytes) -> None:
        msg, _ = decode(episode_control_adapter, payload)
        if isinstance(msg, EpisodeStop):
            return  # the bug
        super()._on_control(payload)


class _StepT:
    """A bus whose Commands after step 0 carry the step of the measurement they answer."""

    def __init__(self, bus, rig: str) -> None:
        self._bus, self._key = bus, keys.command(rig)

    def publish(self, key: str, payload: bytes, express: bool = False) -> None:
        if key == self._key:
            body = json.loads(payload)
            if body["step"] > 0:
                body["step"] -= 1  # the bug
                payload = json.dumps(body).encode()
        self._bus.publish(key, payload, express)

    def __getattr__(self, name):
        return getattr(self._bus, name)


class StepT(ControllerNode):
    def __init__(self, bus, rig: str, *args, **kwargs) -> None:
        super().__init__(_StepT(bus, rig), rig, *args, **kwargs)


class _V10:
    """A bus that serves no rig/{rig}/policies and publishes nothing on result/{rig}/rejected."""

    def __init__(self, bus, rig: str) -> None:
        self._bus, self._rig = bus, rig

    def serve(self, key: str, handler):
        if key == keys.rig_policies(self._rig):
            return _Nothing()
        return self._bus.serve(key, handler)

    def publish(self, key: str, payload: bytes, express: bool = False) -> None:
        if key != keys.episode_rejected(self._rig):
            self._bus.publish(key, payload, express)

    def __getattr__(self, name):
        return getattr(self._bus, name)


class _Nothing:
    def undeclare(self) -> None:
        pass


class V10(ControllerNode):
    def __init__(self, bus, rig: str, *args, **kwargs) -> None:
        super().__init__(_V10(bus, rig), rig, *args, **kwargs)


SETUP_S = 1.0


class _TokenAlready:
    """A bus whose ``announce`` declares nothing: the token is already up."""

    def __init__(self, bus) -> None:
        self._bus = bus

    def announce(self, key: str):
        return _Nothing()

    def __getattr__(self, name):
        return getattr(self._bus, name)


class TokenFirst(ControllerNode):
    def __init__(self, bus, rig: str, *args, **kwargs) -> None:
        self.early_token = bus.announce(keys.alive("controller", rig))  # the bug
        time.sleep(SETUP_S)  # a slow start, say
        super().__init__(_TokenAlready(bus), rig, *args, **kwargs)

    def close(self) -> None:
        super().close()
        self.early_token.undeclare()


BUGS = {"ignores-stop": IgnoresStop, "step-t": StepT, "token-first": TokenFirst, "v1-0": V10}


def main() -> None:
    from ra2vipas.cli.services import run_node, zenoh_settings
    from ra2vipas.services.transport.runtime import configure_logging

    node_class = BUGS[sys.argv.pop(1)]
    parser = argparse.ArgumentParser()
    parser.add_argument("--rig", required=True)
    parser.add_argument("--connect", required=True)
    args = parser.parse_args()
    configure_logging("INFO")
    run_node(f"broken controller[{args.rig}]", zenoh_settings("client", [args.connect], None, None),
             lambda bus: node_class(bus, args.rig))


if __name__ == "__main__":
    main()
