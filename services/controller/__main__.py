"""`python -m ra2vipas.services.controller`: the same as `ra2vipas controller`."""

from ra2vipas.cli.polish import run_function
from ra2vipas.cli.services import controller

if __name__ == "__main__":
    run_function(controller, "python -m ra2vipas.services.controller")
