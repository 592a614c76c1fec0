# The two commands of the README: `make main` (the main job) and `make test` (the tests).
# Both create the virtual environment on first use; it is rebuilt when pyproject.toml changes.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
CORES ?= 2

.PHONY: main test setup dashboard clean-results

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip setuptools wheel
	$(BIN)/pip install --quiet -e '.[test]'
	touch $@

setup: $(VENV)/.installed

main: setup
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/snakemake --cores $(CORES)

test: setup
	PATH="$(abspath $(BIN)):$$PATH" $(BIN)/python -m pytest

dashboard: setup
	$(BIN)/mlflow ui --backend-store-uri sqlite:///$(abspath results)/mlflow.db --host 127.0.0.1 --port $${PORT:-5000}

clean-results:
	rm -rf results logs
