# Two commands, each does its own setup on a fresh machine:  make demo  |  make test
SHELL := /bin/bash
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= demo_out

.PHONY: demo test setup clean-venv

setup: $(STAMP)

# The environment: torch first (the local CPU build; an unpinned torch would pull CUDA
# packages), a system libLLVM >= 16 for Mitsuba's CPU variant, then the package + test extras.
$(STAMP): pyproject.toml scripts/setup_env.sh
	@bash scripts/setup_env.sh "$(PY)" "$(VENV)"
	@touch $(STAMP)

test: $(STAMP)
	$(BIN)/python -m pytest -q

demo: $(STAMP)
	$(BIN)/python scripts/demo.py --out $(DEMO_OUT)

clean-venv:
	rm -rf $(VENV)
