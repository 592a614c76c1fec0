# The two commands of the README: `make main` (the main job) and `make test` (the tests).
# Both create the virtual environment on first use; it is rebuilt when pyproject.toml changes.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
CORES ?= 2
# the scale: SCALE=... on the command line (then remembered in .avatarlab-scale), else the remembered one, else tiny
SCALE ?= $(shell cat .avatarlab-scale 2>/dev/null || echo tiny)
PORT ?= 5000

.PHONY: main test test-fast lint setup system browser cluster unlock dashboard clean-results

# pip --quiet twice: errors only (a machine's pip configuration can add a warning per package: 221 lines here)
$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --quiet --upgrade pip setuptools wheel
	$(BIN)/pip install --quiet --quiet -e '.[test]'
	touch $@

setup: $(VENV)/.installed

# Debian's espeak-ng and Festival with three voices: the voices of the synthetic speech corpus (speech-driven animation);
# graphviz for `snakemake --dag / --rulegraph` pictures (docs/rulegraph.svg)
SPEECH_PACKAGES := espeak-ng festival festvox-kallpc16k festvox-kdlpc16k festvox-us-slt-hts graphviz
system:
	@{ command -v espeak-ng && command -v festival && command -v dot && \
	   [ -d /usr/share/festival/voices/english/kal_diphone ] && \
	   [ -d /usr/share/festival/voices/english/ked_diphone ] && \
	   [ -d /usr/share/festival/voices/us/cmu_us_slt_arctic_hts ]; } >/dev/null 2>&1 || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
	  { apt-get install -y -q $(SPEECH_PACKAGES) >/dev/null 2>&1 || \
	    { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q $(SPEECH_PACKAGES) >/dev/null 2>&1; }; }; } || \
	  echo "note: Debian $(SPEECH_PACKAGES) are not all installed; the speech steps will stop naming what is missing"

# Debian's chromium for the dashboard screenshot test (skipped, with the reason, where it cannot be installed)
browser:
	@command -v chromium >/dev/null 2>&1 || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && \
	  { apt-get install -y -q chromium >/dev/null 2>&1 || \
	    { apt-get update -q >/dev/null 2>&1 && apt-get install -y -q chromium >/dev/null 2>&1; }; }; } || \
	  echo "note: Debian chromium is not installed; the dashboard screenshot test will be skipped"

# Debian's slurm-wlm, munge and postgresql for the one-machine cluster of tests/test_cluster.py (skipped, with the
# reason, where they cannot be installed)
cluster:
	@{ [ "$$(id -u)" = 0 ] && cluster/local_cluster.sh install; } || \
	  echo "note: SLURM / PostgreSQL are not installed; the cluster tests will be skipped"

# the whole reproduction at $(SCALE); then its results card (results/$(SCALE)/report/RESULTS.md: provenance, step
# times, headline tables) and Snakemake's HTML report beside results/$(SCALE)/report/README.md
START := results/.main_$(SCALE).start
main: setup system
	@echo "$(SCALE)" > .avatarlab-scale && echo "avatarlab: scale $(SCALE) (remembered in .avatarlab-scale for later make and snakemake calls)"
	@mkdir -p results && { [ -d results/$(SCALE) ] && state=resumed || state=fresh; echo "$$(date +%s) $$state" > $(START); }
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake --cores $(CORES) --logger avatarlab --config scale=$(SCALE)
	$(BIN)/python -m avatarlab.report.results_card --results results/$(SCALE) --start $(START)
	@mkdir -p logs && PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake --cores $(CORES) --config scale=$(SCALE) \
	  --report results/$(SCALE)/report/workflow_report.html > logs/workflow_report.log 2>&1 && \
	  echo "HTML report: results/$(SCALE)/report/workflow_report.html (its log: logs/workflow_report.log)" || \
	  { tail -20 logs/workflow_report.log; exit 1; }

# two pytest workers (one core each, a test file at a time): the workflow's end-to-end file runs beside the rest
TEST_WORKERS ?= 2
test: setup system browser cluster lint
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile

# the unit tests only (about a minute): what to run after each edit
test-fast: setup
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/python -m pytest -m "not slow"

# ruff (pyflakes, syntax, import order) and Snakemake's own linter
lint: setup
	$(BIN)/ruff check src tests benchmarks
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake --lint >/dev/null 2>lint.log || { cat lint.log; rm -f lint.log; exit 1; }
	@rm -f lint.log

# after the whole workflow was killed (kill, power loss): Snakemake's lock on the directory stays behind
unlock: setup
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake --unlock --cores 1 --config scale=$(SCALE)

dashboard: setup
	$(BIN)/python -m avatarlab.runtime.dashboard --results results --port $(PORT) --scale $(SCALE)

clean-results:
	rm -rf results logs
