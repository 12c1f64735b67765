# Quick start: `make demo` runs the main job, `make test` runs the tests.
# Each target creates .venv and installs the project (with its test extra) on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/v2xpos demo --out out/demo

test: $(STAMP)
	$(BIN)/python -m pytest -q

.PHONY: install demo test
