"""`python -m ra2vipas.services.controller`: the same as `ra2vipas controller`."""

import typer

from ra2vipas.cli.services import controller

if __name__ == "__main__":
    typer.run(controller)
