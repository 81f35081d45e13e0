"""The ``ra2vipas`` console script's entry: Ctrl-C while the command line is still loading.

Importing the command line (numpy, scikit-learn, numba, FastAPI, zenoh...) takes about a second;
a Ctrl-C in that second would print a ``KeyboardInterrupt`` traceback from deep inside some
library's import. Here it ends the command the way a Ctrl-C at any later moment does: one line on
stderr and exit code 130 (128 + SIGINT).
"""

from __future__ import annotations

import sys

INTERRUPTED = 130  # 128 + SIGINT, as cli.polish.run exits on a later Ctrl-C


def main() -> None:
    try:
        from ra2vipas.cli.main import main as run
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        raise SystemExit(INTERRUPTED) from None
    run()
