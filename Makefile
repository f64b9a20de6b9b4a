# Two commands: `make demo` and `make test`. Each creates .venv (Python from .python-version) if missing.
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export SDL_VIDEODRIVER ?= dummy
export MPLBACKEND ?= Agg

.PHONY: demo test lint install clean ffmpeg opengl

$(STAMP): pyproject.toml .python-version
	@$(MAKE) --no-print-directory ffmpeg opengl
	@test -x $(PY) || python3 -m venv $(VENV) || { echo "could not create $(VENV): install Python $$(cat .python-version)"; exit 1; }
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

install: $(STAMP)

# System FFmpeg libraries let torchcodec (LeRobot's preferred video decoder) load: it decodes our 64x64 maze videos
# about 2x faster than PyAV (benchmarks/measure/decoding.py) and spares every LeRobot process a page-long warning.
# Best effort: without root (or passwordless sudo) LeRobot falls back to PyAV, and everything still works.
ffmpeg:
	@if command -v ffmpeg >/dev/null; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ]; then SUDO=; elif sudo -n true 2>/dev/null; then SUDO=sudo; \
	else echo "note: no FFmpeg and no root: video is decoded with PyAV (apt-get install ffmpeg for torchcodec)"; exit 0; fi; \
	{ $$SUDO apt-get update -q >/dev/null && $$SUDO apt-get install -y -q --no-install-recommends ffmpeg >/dev/null; } \
	|| echo "note: could not install FFmpeg: video is decoded with PyAV"

# Offscreen OpenGL (EGL through Mesa, no GPU needed) renders the SO-101 front camera (--env.image_obs=true).
# Best effort, as for FFmpeg: without it that env option says what to install.
opengl:
	@if ldconfig -p | grep -q libEGL_mesa; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ]; then SUDO=; elif sudo -n true 2>/dev/null; then SUDO=sudo; \
	else echo "note: no EGL and no root: the SO-101 camera cannot render (apt-get install libegl1 libgl1-mesa-dri)"; exit 0; fi; \
	{ $$SUDO apt-get update -q >/dev/null && $$SUDO apt-get install -y -q --no-install-recommends libegl1 libegl-mesa0 libgl1-mesa-dri >/dev/null; } \
	|| echo "note: could not install EGL: the SO-101 camera cannot render"

test: $(STAMP)
	$(VENV)/bin/ruff check lerobot_iupe lerobot_policy_iupe.py scripts benchmarks tests
	$(VENV)/bin/ruff format --check lerobot_iupe lerobot_policy_iupe.py scripts benchmarks tests
	$(PY) -m pytest -q -n 2 --durations=25

demo: $(STAMP)
	$(PY) scripts/demo.py

clean:
	rm -rf outputs/demo
