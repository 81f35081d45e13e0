"""`python -m services.orchestrator`: the same as `ra2vipas orchestrator`."""

import typer

from cli.services import orchestrator

if __name__ == "__main__":
    typer.run(orchestrator)
