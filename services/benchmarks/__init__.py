"""The speed benchmarks the project ships: what ``ra2vipas bench ...`` runs and prints.

One module per harness (``step``, ``learner``, ``simulate``, ``mesh``, ``orchestrator``,
``plots``, ``dashboard``); each is a function of plain arguments that returns its report, a
JSON-ready dict. The command line (cli/bench.py) parses and validates the options, shows
progress and prints; nothing here imports it. A harness that runs a local stack of processes is
handed a ``common.StackFactory`` by its caller (the CLI's is cli/stack.py's ``Stack``).

A harness that cannot finish raises ``BenchmarkError`` with a one-line message.
"""

from __future__ import annotations


class BenchmarkError(Exception):
    """A benchmark that could not finish (a stack that did not start, a campaign that failed or
    timed out, a probe process that died); its message is one line."""
