"""`python -m services.sensors`: the same as `ra2vipas sensors`."""

import typer

from cli.services import sensors

if __name__ == "__main__":
    typer.run(sensors)
