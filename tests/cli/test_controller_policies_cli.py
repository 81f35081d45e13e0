"""``ra2vipas controller --policy NAME`` (repeatable, comma-separated, or RA2VIPAS_POLICY): the
policies a controller serves, checked before it joins the network (issue 19)."""

from __future__ import annotations

from ra2vipas.cli.services import served_policies
from ra2vipas.services.controller.registry import BUILTINS
from tests.cli.conftest import one_error_line, ra2vipas


def test_policies_are_repeatable_or_comma_separated_and_default_to_every_installed_one():
    assert list(served_policies(["rapas,sweep", "ra2vipas", "rapas"])) == ["rapas", "sweep", "ra2vipas"]
    assert list(served_policies(None))[:4] == list(BUILTINS)
    spin = served_policies(["tests.nodes.test_policy_mesh:Spin"])
    assert spin == {"spin": "tests.nodes.test_policy_mesh:Spin"}  # module:Class is served under its class's name


def test_a_policy_that_does_not_load_is_one_error_line_before_joining_the_network():
    for args, env in ((["--policy", "nope"], None), ([], {"RA2VIPAS_POLICY": "rapas,nope"})):
        proc = ra2vipas("controller", "--rig", "rig-1", "--connect", "tcp/127.0.0.1:9", *args, env=env, timeout=60)
        assert proc.returncode == 2, proc.stderr
        assert one_error_line(proc).startswith("error: unknown policy 'nope'; installed: ra2vipas, rapas, ravipas, sweep")


def test_the_help_names_the_option_and_its_variable():
    proc = ra2vipas("controller", "--help")
    assert proc.returncode == 0 and "--policy" in proc.stdout and "RA2VIPAS_POLICY" in proc.stdout
