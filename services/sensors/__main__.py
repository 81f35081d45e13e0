"""`python -m ra2vipas.services.sensors`: the same as `ra2vipas sensors`."""

from ra2vipas.cli.polish import run_function
from ra2vipas.cli.services import sensors

if __name__ == "__main__":
    run_function(sensors, "python -m ra2vipas.services.sensors")
