# Quick start: `make demo` runs the main job, `make test` runs all the tests (what CI runs),
# `make test-fast` the loop to run while developing (everything but the tests marked slow).
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

# Debian packages the browser test needs (headless Chromium + its WebDriver); installed only when
# missing, as root (CI) or through sudo; otherwise the test says why it is skipped.
browser-deps:
	@if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then :; \
	elif ! command -v apt-get >/dev/null; then echo "browser-deps: no apt-get; browser test will be skipped"; \
	elif [ "$$(id -u)" = 0 ]; then apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null || echo "browser-deps: apt-get install failed; browser test will be skipped"; \
	elif command -v sudo >/dev/null && sudo -n true 2>/dev/null; then sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null || echo "browser-deps: apt-get install failed; browser test will be skipped"; \
	else echo "browser-deps: not root; install chromium chromium-driver to run the browser test"; fi

demo: $(STAMP)
	$(BIN)/v2xpos demo --out out/demo

# tests run on every core (pytest-xdist), a test file per worker at a time so that a module's
# expensive fixtures (recordings replayed once, shared by its tests) are built once
test: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadfile

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadfile -m "not slow"

.PHONY: install demo test test-fast browser-deps
