# Two commands do all the set-up on a fresh machine:  `make demo` (the main job) and `make test` (the tests; the
# end-to-end tests marked `slow` run in `make test-all`, which CI runs).
# Both create .venv on first use: CPU torch 2.13.0 first (a bare `torch` would pull a multi-GB CUDA build),
# then the package with its dev extra. Everything runs offline.
PY ?= python3
VENV := .venv
# extra pip arguments for torch, e.g. TORCH_PIP_ARGS="--index-url https://download.pytorch.org/whl/cpu" (Docker)
TORCH_PIP_ARGS ?=
BIN := $(VENV)/bin
export WANDB_MODE ?= offline
export HF_HUB_OFFLINE := 1
export HF_DATASETS_OFFLINE := 1
export PIP_DISABLE_PIP_VERSION_CHECK := 1

.PHONY: install demo test test-all lint bench figures

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q torch==2.13.0 $(TORCH_PIP_ARGS)
	$(BIN)/pip install -q -e ".[dev]"
	touch $@

demo: $(VENV)/.installed
	$(BIN)/ttompc demo

test: $(VENV)/.installed lint
	$(BIN)/python -m pytest -q -m "not slow"

test-all: $(VENV)/.installed lint
	$(BIN)/python -m pytest -q

lint: $(VENV)/.installed
	$(BIN)/ruff check ttompc tests bench examples
	$(BIN)/ruff format --check ttompc tests bench examples
	$(BIN)/mypy  # the package, configured in pyproject.toml [tool.mypy]

bench: $(VENV)/.installed
	for b in bench/*.py; do $(BIN)/python $$b || exit 1; done
