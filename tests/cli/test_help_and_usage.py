"""How the command line presents itself (issue 13): help reflowed to the terminal, no `<bool>`
on flags, usage lines without `{campaign_id}`, no stray ` .`, the orchestrator's defaults and
environment variables shown, examples in the everyday commands' help; usage errors (a range,
an unknown option, a missing argument) in one line with exit 2; renamed options and commands
keep their old spelling with a warning."""

from __future__ import annotations

import re

import pytest
import typer

from ra2vipas.cli.main import app
from ra2vipas.cli.polish import polish, run
from ra2vipas.cli.stack import free_port
from tests.cli.conftest import one_error_line, ra2vipas

WIDTH = 150  # wider than any docstring line, so a line break kept from the source shows
BOX = "│╭╮╰╯─"


def _paths(command, prefix=()):
    """Every command path of the CLI, groups included."""
    yield prefix
    for name, sub in getattr(command, "commands", {}).items():
        if not sub.hidden:
            yield from _paths(sub, (*prefix, name))


PATHS = list(_paths(typer.main.get_command(app)))


def _help(path, capsys, monkeypatch) -> str:
    monkeypatch.setenv("COLUMNS", str(WIDTH))
    monkeypatch.setenv("TERMINAL_WIDTH", str(WIDTH))
    with pytest.raises(SystemExit) as done:
        run(app, [*path, "--help"])
    assert done.value.code == 0
    return capsys.readouterr().out


def _description(text: str) -> list[list[str]]:
    """The paragraphs of a help page's description (between the usage line and the first box)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith("Usage:")) + 1
    body = []
    for line in lines[start:]:
        if line.strip() and line.strip()[0] in BOX:
            break
        body.append(line.rstrip())
    paragraphs, current = [], []
    for line in body:
        if line.strip():
            current.append(line)
        elif current:
            paragraphs.append(current)
            current = []
    return paragraphs + ([current] if current else [])


def test_the_cli_has_the_commands_we_expect():
    assert {("campaign", "start"), ("campaign", "plot"), ("rigs", "list"), ("up",), ("orchestrator",)} <= set(PATHS)


@pytest.mark.parametrize("path", PATHS, ids=lambda p: " ".join(p) or "ra2vipas")
def test_help_is_reflowed_without_bool_braces_or_stray_dots(path, capsys, monkeypatch):
    text = _help(path, capsys, monkeypatch)
    assert "<bool>" not in text
    usage = next(line for line in text.splitlines() if "Usage:" in line)
    assert "{" not in usage and "}" not in usage, usage
    assert not re.search(r"\w \.(\s|$)", text), "a stray ' .' (markup eaten from the help text)"
    paragraphs = _description(text)
    assert paragraphs, text
    for paragraph in paragraphs:
        prose = [line for line in paragraph if not line.strip().startswith("ra2vipas ")]  # examples keep their lines
        for line in prose[:-1]:  # every line of a reflowed paragraph but its last fills the width
            assert len(line) > WIDTH - 30, f"help of {' '.join(path)} breaks early: {line!r}"


def test_usage_names_the_argument_in_capitals(capsys, monkeypatch):
    text = _help(("campaign", "results"), capsys, monkeypatch)
    assert "Usage: ra2vipas campaign results [OPTIONS] CAMPAIGN_ID" in text
    assert "Usage: ra2vipas campaign plot [OPTIONS] CAMPAIGN_ID..." in _help(("campaign", "plot"), capsys, monkeypatch)


def test_the_orchestrator_help_shows_defaults_and_environment_variables(capsys, monkeypatch):
    text = " ".join(_help(("orchestrator",), capsys, monkeypatch).replace("│", " ").split())
    for needle in ("RA2VIPAS_HOST; default 127.0.0.1", "RA2VIPAS_PORT; default 8080", "RA2VIPAS_DB; default ra2vipas.db",
                   "RA2VIPAS_WINDOW; default 8", "RA2VIPAS_EXPECT_RIGS; default 1",
                   "RA2VIPAS_ZENOH_MODE; default client with --connect and no --listen"):
        assert needle in text, needle


@pytest.mark.parametrize("path", [("simulate",), ("up",), ("campaign", "start"), ("campaign", "watch"), ("campaign", "results"),
                                  ("campaign", "plot"), ("campaign", "export"), ("campaign", "list"), ("study", "start"),
                                  ("rigs", "list"), ("router",)])
def test_everyday_commands_show_examples(path, capsys, monkeypatch):
    text = _help(path, capsys, monkeypatch)
    assert re.search(r"Examples?:", text)
    assert f"ra2vipas {' '.join(path)} " in text


def test_polish_is_idempotent():
    command = polish(polish(typer.main.get_command(app)))
    assert command.commands["campaign"].commands["results"].params[0].metavar == "CAMPAIGN_ID"


@pytest.mark.parametrize("args, words", [
    (("simulate", "--tests", "0"), "Invalid value for '--tests'"),
    (("campaign", "start", "--tests", "100000"), "Invalid value for '--tests'"),
    (("simulate", "--stop-confidence", "1.5"), "Invalid value for '--stop-confidence'"),
    (("up", "--port", "0"), "Invalid value for '--port'"),
    (("campaign", "results"), "Missing argument 'CAMPAIGN_ID'"),
    (("campaign", "start", "--frobnicate"), "No such option: --frobnicate"),
    (("campaign", "resutls"), "No such command 'resutls'"),
])
def test_usage_errors_are_one_line_and_exit_2(args, words):
    proc = ra2vipas(*args)
    assert proc.returncode == 2, proc
    line = one_error_line(proc)
    assert words in line and line.endswith("--help`)"), line


def test_one_tests_cap_for_simulate_campaign_and_study():
    for args in (("simulate",), ("campaign", "start"), ("study", "start", "--vary", "n_targets=5,6")):
        proc = ra2vipas(*args, "--tests", "10001")
        assert proc.returncode == 2 and "less than or equal to 10000" in one_error_line(proc), args


def test_the_old_spelling_of_rig_count_still_works_with_a_warning(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    proc = ra2vipas("up", "--rigs", "2", "--port", str(free_port()), "--db", str(blocker / "sub" / "x.db"), timeout=60)
    lines = proc.stderr.strip().splitlines()
    assert lines[0] == "warning: --rigs is deprecated; use --rig-count"
    assert proc.returncode == 1 and lines[-1].startswith("error: ") and "database" in lines[-1]
    bad = ra2vipas("up", "--rigs", "0")
    assert bad.returncode == 2 and "Invalid value for '--rigs'" in one_error_line(bad)


def test_python_m_services_run_the_same_commands():
    import subprocess
    import sys

    for name in ("sensors", "controller", "learner", "orchestrator"):
        proc = subprocess.run([sys.executable, "-m", f"ra2vipas.services.{name}", "--help"], capture_output=True, text=True,
                              timeout=60)
        assert proc.returncode == 0 and f"python -m ra2vipas.services.{name}" in proc.stdout, name
    bad = subprocess.run([sys.executable, "-m", "ra2vipas.services.learner", "--frobnicate"], capture_output=True, text=True,
                         timeout=60)
    assert bad.returncode == 2 and one_error_line(bad).startswith("error: No such option: --frobnicate")


@pytest.mark.parametrize("variable, value, words", [
    ("RA2VIPAS_PORT", "80a", "Invalid value for '--port' (env var: 'RA2VIPAS_PORT')"),
    ("RA2VIPAS_PORT", "0", "Invalid value for '--port' (env var: 'RA2VIPAS_PORT')"),
])
def test_bad_environment_values_for_up_are_one_line(variable, value, words):
    proc = ra2vipas("up", env={variable: value})
    assert proc.returncode == 2 and words in one_error_line(proc)
