"""`python -m ra2vipas.services.learner`: the same as `ra2vipas learner`."""

import typer

from ra2vipas.cli.services import learner

if __name__ == "__main__":
    typer.run(learner)
