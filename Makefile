# Two entry points for a fresh machine (see README):
#   make campaign   set up .venv and run the paper campaign
#   make test       set up .venv, install the system Chromium if missing, run ruff check and the test suite
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CHROMIUM ?= /usr/bin/chromium
STAMP  := $(VENV)/.installed

.PHONY: setup browser campaign test bench docs clean

setup: $(STAMP)

# An editable install of a package whose subpackages live in other folders (services/, cli/) goes
# through setuptools' import finder, which says so in an 8-line "Editable installation." notice:
# information only, silenced here (tests/packaging checks the install prints no warning).
EDITABLE_QUIET := PYTHONWARNINGS="ignore:Editable installation"

# A set-up interrupted while the venv was being made leaves one without pip: make it again.
# The pinned set is installed with uv (Astral's installer: pip's job, resolving and unpacking in
# parallel; 25-47 s here where pip took 59-66 s, for every fresh clone and CI run), itself
# pinned in constraints.txt and fetched with pip. It compiles the libraries' bytecode as pip does.
# uv does not read pip's configuration: where it cannot install (an index only pip.conf knows, no
# uv wheel for the platform), pip does, as before.
$(STAMP): pyproject.toml constraints.txt
	@if [ ! -x $(BIN)/pip ]; then rm -rf $(VENV) && echo "$(PYTHON) -m venv $(VENV)" && $(PYTHON) -m venv $(VENV); fi
	@if $(BIN)/pip install --quiet -c constraints.txt uv 2>/dev/null && \
	    $(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -c constraints.txt -e '.[test]'; then \
	    echo "installed the pinned set with uv"; \
	else \
	    echo "uv could not install the pinned set: installing it with pip"; \
	    $(BIN)/pip install --quiet --upgrade pip && \
	    $(EDITABLE_QUIET) $(BIN)/pip install --quiet -c constraints.txt -e '.[test]'; \
	fi
	touch $(STAMP)

campaign: setup
	mkdir -p results
	$(BIN)/ra2vipas campaign start --embedded --preset paper --tests 50 --seed 1 --db results/ra2vipas.db --plot results/dr-paper.png

# The dashboard's browser tests drive the Debian package's Chromium through Playwright (Playwright's
# own browser download is not used): install it when it is missing (apt-get needs root, or sudo).
browser: $(CHROMIUM)

$(CHROMIUM):
	@if [ "$$(id -u)" = 0 ]; then SUDO=; elif command -v sudo >/dev/null 2>&1; then SUDO=sudo; \
	else echo "error: $(CHROMIUM) is missing and installing the Debian package chromium needs root" >&2; exit 1; fi; \
	$$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium >/dev/null

# The suite starts ~500 Python processes. pip compiles the installed libraries' bytecode, but not an
# editable install's own source; with PYTHONDONTWRITEBYTECODE set (as in many containers and CI
# images) every process would compile the project's modules again (~0.3 s of CPU each):
# compileall writes them once (it skips what is up to date).
# The numba kernels are compiled once into their on-disk cache before the suite (tools/warm_kernels.py:
# for this CPU and, side by side, for the generic CPU of tests/docs/test_other_cpus.py), rather than
# by every process of the suite's first minutes that calls one before the cache holds it.
test: setup browser
	$(BIN)/ruff check .
	$(BIN)/python -m compileall -q -j 0 ra2vipas services cli
	$(BIN)/python tools/warm_kernels.py & NUMBA_CPU_NAME=generic $(BIN)/python tools/warm_kernels.py; s=$$?; wait $$! && exit $$s
	$(BIN)/pytest -q -n 2 --dist loadfile

# The README's result tables and figure from what the code prints (minutes): reruns the documented
# campaigns and benchmarks, writes docs/results.json, renders the README blocks from it.
docs: setup
	$(BIN)/python tools/docs.py

bench: setup
	$(BIN)/ra2vipas bench step --json

clean:
	rm -rf $(VENV) results .pytest_cache
