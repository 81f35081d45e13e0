"""A deliberately broken hardware node for the conformance kit's test: the reference node of
examples/hardware_node, except that it ignores EpisodeStop (it keeps answering the commands of
a stopped episode)."""

import importlib.util
import sys
from pathlib import Path

spec = importlib.util.spec_from_file_location(
    "hardware_node", Path(__file__).resolve().parents[2] / "examples" / "hardware_node" / "hardware_node.py")
example = importlib.util.module_from_spec(spec)
sys.modules["hardware_node"] = example
spec.loader.exec_module(example)


class IgnoresStop(example.HardwareNode):
    def on_control(self, sample) -> None:
        msg = self.parse(sample)
        if msg is not None and msg.get("kind") == "stop":
            return  # the bug
        super().on_control(sample)


if __name__ == "__main__":
    example.main(node_class=IgnoresStop)
