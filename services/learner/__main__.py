"""`python -m services.learner`: the same as `ra2vipas learner`."""

import typer

from cli.services import learner

if __name__ == "__main__":
    typer.run(learner)
