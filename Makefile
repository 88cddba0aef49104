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

# The README's figures in docs/figures/ (ttompc.evaluation.figures), each drawn from the report of the command below,
# which runs only when its report is missing: the warm-start report in about 1.5 CPU-minutes; the closed-loop sweeps
# (Fig. 5 and 6: H = 10, 20, ..., 100, both plants, 100 problems per scenario) take hours on all cores, store each
# episode as it finishes and resume where they stopped when run again (docs/evaluation.md, "Sweeps").
# Other reports: make figures FIG_MPC="a/mpc.json b/mpc.json" FIG_WARMSTART=path/warmstart.json
SWEEP := horizons=[10,20,30,40,50,60,70,80,90,100] problems=100 seed=4242 protocol=recommended
FIG_MPC ?= outputs/figures/mpc-freeflyer/mpc.json outputs/figures/mpc-quadrotor/mpc.json \
	outputs/figures/mpc-rpod/mpc.json
FIG_WARMSTART ?= outputs/figures/warmstart-freeflyer/warmstart.json

outputs/figures/mpc-freeflyer/mpc.json: | $(VENV)/.installed
	$(BIN)/ttompc evaluate mpc --model freeflyer-tto-v3 --ft-model freeflyer-ft-tto-v5 $(SWEEP) out=$(@D)

outputs/figures/mpc-quadrotor/mpc.json: | $(VENV)/.installed
	$(BIN)/ttompc evaluate mpc --model quadrotor-tto-v3 --ft-model quadrotor-ft-tto-v6 $(SWEEP) out=$(@D)

outputs/figures/mpc-rpod/mpc.json: | $(VENV)/.installed
	$(BIN)/ttompc evaluate mpc --model rpod-tto-v3 --ft-model rpod-ft-tto-v4 $(SWEEP) out=$(@D)

outputs/figures/warmstart-freeflyer/warmstart.json: | $(VENV)/.installed
	$(BIN)/ttompc evaluate warmstart --model freeflyer-tto-v3 --ft-model freeflyer-ft-tto-v5 problems=100 seed=4242 \
		workers=1 out=$(@D)

figures: $(VENV)/.installed $(FIG_MPC) $(FIG_WARMSTART)
	$(BIN)/python -m ttompc.evaluation.figures --mpc $(FIG_MPC) --warmstart $(FIG_WARMSTART) --out docs/figures
