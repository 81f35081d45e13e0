"""`python -m ra2vipas.services.orchestrator`: the same as `ra2vipas orchestrator`."""

import typer

from ra2vipas.cli.services import orchestrator

if __name__ == "__main__":
    typer.run(orchestrator)
