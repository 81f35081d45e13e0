"""Ctrl-C at any moment of a command, even while it is still importing its libraries, ends it
with one line on stderr and exit code 130, never a traceback."""

from __future__ import annotations

import subprocess
import sys

import pytest
import typer

from ra2vipas.cli.polish import run
from tests.cli.conftest import ROOT

INTERRUPT_THE_IMPORT = """
import builtins
real_import = builtins.__import__
def interrupted_import(name, *args, **kw):
    if name == "ra2vipas.cli.main":
        raise KeyboardInterrupt  # what a Ctrl-C in the middle of importing the command line raises
    return real_import(name, *args, **kw)
builtins.__import__ = interrupted_import
from ra2vipas.cli.launch import main
main()
"""


def test_a_ctrl_c_while_the_command_line_imports_is_one_line_and_exit_130():
    done = subprocess.run([sys.executable, "-c", INTERRUPT_THE_IMPORT], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert (done.returncode, done.stderr, done.stdout) == (130, "interrupted\n", "")


def test_a_ctrl_c_inside_a_command_is_exit_130_not_an_error():
    app = typer.Typer()

    @app.command()
    def wait() -> None:
        raise KeyboardInterrupt

    with pytest.raises(SystemExit) as ended:
        run(app, argv=[])
    assert ended.value.code == 130


def test_importing_the_package_loads_no_library_so_a_ctrl_c_meets_the_guard_at_once():
    """Before ``ra2vipas.cli.launch`` can catch a Ctrl-C, Python imports the package ``ra2vipas``:
    it must load nothing heavy (its public names load on first use), so that the unguarded
    window is the interpreter's own start, not a second of numpy, httpx and FastAPI."""
    code = ("import sys, ra2vipas, ra2vipas.cli.launch; "
            "print(sorted(m for m in ('numpy', 'httpx', 'fastapi', 'zenoh', 'typer', 'pydantic') if m in sys.modules)); "
            "print(ra2vipas.Policy.__name__, ra2vipas.simulate.__name__, 'Client' in dir(ra2vipas))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["[]", "Policy simulate True"]
