"""`python -m services.controller`: the same as `ra2vipas controller`."""

import typer

from cli.services import controller

if __name__ == "__main__":
    typer.run(controller)
