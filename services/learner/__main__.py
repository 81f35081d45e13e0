"""`python -m ra2vipas.services.learner`: the same as `ra2vipas learner`."""

from ra2vipas.cli.polish import run_function
from ra2vipas.cli.services import learner

if __name__ == "__main__":
    run_function(learner, "python -m ra2vipas.services.learner")
