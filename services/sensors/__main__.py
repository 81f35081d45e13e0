"""`python -m ra2vipas.services.sensors`: the same as `ra2vipas sensors`."""

import typer

from ra2vipas.cli.services import sensors

if __name__ == "__main__":
    typer.run(sensors)
