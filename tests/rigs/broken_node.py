"""Deliberately broken hardware nodes for the conformance kit's tests: the reference node of
examples/hardware_node with one bug each, chosen by the first argument.

    python broken_node.py ignores-stop --rig bad-1 --connect tcp/ROUTER:7447
    python broken_node.py token-first --rig bad-2 --connect tcp/ROUTER:7447

* ``ignores-stop``: it keeps answering the commands of a stopped episode;
* ``token-first``: it declares its liveliness token before anything else, then takes
  ``SETUP_S`` to declare its subscriptions and queryables (whoever acts on the token at once,
  as the orchestrator does, is not heard).
"""

import importlib.util
import sys
import time
from pathlib import Path

spec = importlib.util.spec_from_file_location(
    "hardware_node", Path(__file__).resolve().parents[2] / "examples" / "hardware_node" / "hardware_node.py")
example = importlib.util.module_from_spec(spec)
sys.modules["hardware_node"] = example
spec.loader.exec_module(example)

SETUP_S = 1.0


class IgnoresStop(example.HardwareNode):
    def on_control(self, sample) -> None:
        msg = self.parse(sample)
        if msg is not None and msg.get("kind") == "stop":
            return  # the bug
        super().on_control(sample)


class TokenFirst(example.HardwareNode):
    def __init__(self, session, rig: str, *args, **kwargs) -> None:
        self.early_token = session.liveliness().declare_token(f"{example.PREFIX}/alive/sensors/{rig}")  # the bug
        time.sleep(SETUP_S)  # a slow driver, say
        super().__init__(session, rig, *args, **kwargs)

    def close(self) -> None:
        super().close()
        self.early_token.undeclare()


BUGS = {"ignores-stop": IgnoresStop, "token-first": TokenFirst}

if __name__ == "__main__":
    node_class = BUGS[sys.argv.pop(1)]
    example.main(node_class=node_class)
