# Two commands: `make demo` and `make test`. Each creates .venv (Python from .python-version) if missing.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export SDL_VIDEODRIVER ?= dummy
export MPLBACKEND ?= Agg

.PHONY: demo test lint install clean

$(STAMP): pyproject.toml .python-version
	@test -x $(PY) || python3 -m venv $(VENV) || { echo "could not create $(VENV): install Python $$(cat .python-version)"; exit 1; }
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	$(VENV)/bin/ruff check lerobot_iupe lerobot_policy_iupe.py scripts tests
	$(VENV)/bin/ruff format --check lerobot_iupe lerobot_policy_iupe.py scripts tests
	$(PY) -m pytest -q

demo: $(STAMP)
	$(PY) scripts/demo.py

clean:
	rm -rf outputs/demo
