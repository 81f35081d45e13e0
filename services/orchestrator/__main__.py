"""`python -m ra2vipas.services.orchestrator`: the same as `ra2vipas orchestrator`."""

from ra2vipas.cli.polish import run_function
from ra2vipas.cli.services import orchestrator

if __name__ == "__main__":
    run_function(orchestrator, "python -m ra2vipas.services.orchestrator")
