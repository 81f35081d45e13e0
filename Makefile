# Two entry points for a fresh machine (see README):
#   make campaign   set up .venv and run the paper campaign
#   make test       set up .venv and run the test suite
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup campaign test bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

campaign: setup
	mkdir -p results
	$(BIN)/ra2vipas campaign start --embedded --preset paper --tests 50 --seed 1 --db results/ra2vipas.db --plot results/dr-paper.png

test: setup
	$(BIN)/pytest -q

bench: setup
	$(BIN)/ra2vipas bench step --json

clean:
	rm -rf $(VENV) results .pytest_cache
