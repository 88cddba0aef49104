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

.PHONY: install demo test test-all lint bench figures figures-plan FORCE

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

# The README's figures in $(FIG_OUT) (ttompc.evaluation.figures) and the speedup-at-equal-cost table $(FIG_TABLE),
# each drawn from the report of a command below: the warm-start report (about 1.5 CPU-minutes) when it is missing;
# the closed-loop sweeps (Fig. 5 and 6, both plants, every scenario of FIG_SCENARIOS) every time: a sweep stores each
# episode as it finishes, resumes where it stopped and extends to a larger grid or more problems in the same folder
# (docs/evaluation.md, "Sweeps"); a finished one only writes its report again. Before each sweep its cost is printed
# ("about N CPU-hours", from docs/sweep-cost.json); `make figures-plan` prints every grid's and what FIG_BUDGET buys.
# Grids (FIG_GRID): reduced (default, a few CPU-hours per scenario), paper (the paper's H = 10, 20, ..., 100),
# minimal (H = 10 and 30, the equal-cost table's); e.g. make figures FIG_GRID=paper FIG_PROBLEMS=500.
# The sweeps keep the paper's fixed horizon (mpc.end_horizon=0: windows truncated at N), so that H is the one variable
# of the figures; protocol=recommended's shrinking end horizon is measured in the cards.
# Smoke run: make figures FIG_GRID=minimal FIG_PROBLEMS=2 FIG_RUNS=/tmp/runs FIG_OUT=/tmp/figs FIG_TABLE=/tmp/t.md
# Run one sweep at a time (no make -j): each uses FIG_WORKERS cores.
FIG_GRID ?= reduced
FIG_PROBLEMS ?= 100
FIG_WORKERS ?= 2
FIG_PLANTS ?= [nominal,perturbed]
FIG_BUDGET ?= 3
FIG_SCENARIOS ?= freeflyer quadrotor rpod
FIG_RUNS ?= outputs/figures
FIG_OUT ?= docs/figures
FIG_TABLE ?= docs/equal-cost.md
FIG_HORIZONS_minimal := [10,30]
FIG_HORIZONS_reduced := [10,20,30,50,100]
FIG_HORIZONS_paper := [10,20,30,40,50,60,70,80,90,100]
FIG_MODELS_freeflyer ?= --model freeflyer-tto-v3 --ft-model freeflyer-ft-tto-v5
FIG_MODELS_quadrotor ?= --model quadrotor-tto-v3 --ft-model quadrotor-ft-tto-v6
FIG_MODELS_rpod ?= --model rpod-tto-v3 --ft-model rpod-ft-tto-v4
FIG_HORIZONS = $(FIG_HORIZONS_$(FIG_GRID))
SWEEP = horizons=$(FIG_HORIZONS) problems=$(FIG_PROBLEMS) plants=$(FIG_PLANTS) seed=4242 protocol=recommended \
	mpc.end_horizon=0 workers=$(FIG_WORKERS)
# Other reports: make figures FIG_MPC="a/mpc.json b/mpc.json" FIG_WARMSTART=path/warmstart.json
FIG_MPC ?= $(foreach s,$(FIG_SCENARIOS),$(FIG_RUNS)/mpc-$(s)/mpc.json)
FIG_WARMSTART ?= $(FIG_RUNS)/warmstart-freeflyer/warmstart.json
FIG_WARMSTART_PROBLEMS ?= 100

$(FIG_RUNS)/mpc-%/mpc.json: FORCE | $(VENV)/.installed
	$(if $(FIG_HORIZONS),,$(error FIG_GRID=$(FIG_GRID): not minimal, reduced or paper))
	-$(BIN)/python -m ttompc.evaluation.sweep_cost estimate --scenario $* --problems $(FIG_PROBLEMS) \
		--horizons $(FIG_HORIZONS) --plants $(FIG_PLANTS) --workers $(FIG_WORKERS)
	$(BIN)/ttompc evaluate mpc $(FIG_MODELS_$*) $(SWEEP) out=$(@D)

$(FIG_WARMSTART): | $(VENV)/.installed
	$(BIN)/ttompc evaluate warmstart $(FIG_MODELS_freeflyer) problems=$(FIG_WARMSTART_PROBLEMS) seed=4242 \
		workers=1 out=$(@D)

FORCE:

figures: $(VENV)/.installed $(FIG_MPC) $(FIG_WARMSTART)
	$(BIN)/python -m ttompc.evaluation.figures --mpc $(FIG_MPC) --warmstart $(FIG_WARMSTART) --out $(FIG_OUT) \
		--table $(FIG_TABLE)

figures-plan: $(VENV)/.installed
	$(BIN)/python -m ttompc.evaluation.sweep_cost plan --budget $(FIG_BUDGET) --plants $(FIG_PLANTS)
