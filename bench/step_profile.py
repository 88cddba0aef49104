"""Where an MPC step's time goes: the mean step of the shipped model's TTO-family MPC at H = 10
(``protocol=recommended``: FT-TTO-MPC and its robust variant R-FT-TTO-MPC, fed the model's value output as
reward-to-go) beside REL-MPC at H = 30 (``protocol=paper``), on every scenario, in one run, split into its parts.

Usage::

    nice -n 19 env OMP_NUM_THREADS=1 .venv/bin/python bench/step_profile.py            # all three scenarios
    .venv/bin/python bench/step_profile.py --scenario quadrotor --problems 20 --batch 1
    .venv/bin/python bench/step_profile.py --quick                                    # smoke run, no result file
    .venv/bin/python bench/step_profile.py --mpc rti=true --out bench/results/step_profile_rti.json  # a lever
    .venv/bin/python bench/step_profile.py --mpc decode_every=5 --out bench/results/step_profile_decode5.json
    .venv/bin/python bench/step_profile.py --mpc decoder=fused --out bench/results/step_profile_fused.json

Models: ``freeflyer-ft-tto-v5``, ``quadrotor-ft-tto-v6`` and ``rpod-ft-tto-v4``, fine-tuned with a value output, run
as ``ttompc evaluate mpc --ft-model`` runs them (``rtg_mode=value`` under ``protocol=recommended``:
FT-TTO-MPC[rtg=value], R-FT-TTO-MPC[rtg=value]); ``--model SCENARIO=SOURCE`` replaces one (a model whose name has no
``ft`` runs as ``--model``: TTO-MPC, R-TTO-MPC). Problems: the first ``--problems`` held-out non-convex problems of
root seed ``--seed`` (4242, as in docs/evaluation.md; ``eval_problem``). Episodes: the nominal plant, all N steps (or
``--max-steps``), the problems in lockstep in tasks of ``--batch`` (10, ``ttompc evaluate mpc``'s default: one
batched rollout per step for a TTO method, each episode charged its share; ``--batch 1``: one robot's latency), one
process (``workers=1``), one torch thread. The providers come from the methods' own factories (``ttompc.mpc.methods``,
as ``evaluate mpc`` makes them) with the settings of ``ClosedLoopConfig(protocol=...)``, so the methods are the
evaluation's; each method first runs one warm-up episode on problem 0 outside the timing (imports, torch
kernels, the solver structures of every window shape), so the profile is the steady state.

Instrumentation: the bench wraps library functions with ``time.perf_counter`` timers by monkeypatching (restored at
the end; nothing in the library changes, and ``--verify``, on with ``--quick``, reruns each method without the
timers and checks that the executed controls are identical). A step is ``MPCController.plan`` (warm start + window
SCP) and then ``MPCController.observe`` (the executed control and the next state handed to the provider), the wall
time of the two calls. The loop's own record, ``Episode.step_times``, is reported beside it (``loop_step_ms``); it
charges each observe to the step that plans from its state, so it holds T − 1 of an episode's T observes, the profile
all T. Timed regions nest; each part below is the time spent in it *exclusive* of the parts nested in it, so the
parts sum to the step:

* ``rollout``: ``RolloutContext.rollout``, the transformer rollout (the shared batched one, charged 1/B per episode,
  or the lone one at ``--batch 1``);
* ``conditioning``: ``TTOProvider.conditioning``, the reward-to-go fed at the step (``rtg_mode=value``: the model's
  value output, ``Planner.cost_to_go``, one batched call per step for the group, charged 1/B, or the lone one at
  ``--batch 1``; ``running``: nothing to compute);
* ``terminal``: terminal design, the target construction (``TargetFilter`` for TTO-MPC, ``providers._terminal`` for
  REL-MPC);
* ``rel_warm_start``: REL-MPC's remaining-horizon REL (``RemainingREL``: itself an SCP or one convex solve);
* ``scp_setup``: the window SCP's linearisation and constraint blocks (``Scenario.convex_model``,
  ``Scenario.constraints``, once per SCP iteration);
* ``scp_solve``: the window SCP's subproblem solver calls (``SubproblemSolver.solve``: writing the iteration's values
  into the built structure and the backend's solve);
* ``scp_bookkeeping``: the rest of the SCP engine (merit, nonlinear violation, stopping rule, solver look-up);
* ``overhead``: the rest of the plan in Python (plan reuse check, warm-start conversions and copies, the rollout
  group's tensor-to-array copies, the loop's shape checks);
* ``observe``: ``MPCController.observe`` after the step's control is executed (TTO: ``TTOProvider.observe``, the
  KV-cache extension ``RolloutContext.advance``, reported alone as ``advance_ms``, once per lockstep step for the
  group, charged 1/B per episode; with ``--mpc decode_every=K`` > 1 the advance only records the step and the next
  decode's ``rollout`` extends the cache over the K steps in one pass).

Reported per method: ``mean_step_ms`` (plan + observe; ``plan_ms`` without observe) and the share of each part,
window SCP iterations per step (and per solved step, with their histogram), the time per subproblem call and per
linearisation, steps served by plan reuse, and the share of window subproblems the Riccati kernel solved
(``kernel_share``; the rest went to the conic chain behind it). Ratio: REL-MPC@30's mean step over each TTO method's
(``ratio_rel30_over``). The model's time: the step's calls of the model, the rollout, the value output and the
KV-cache advance (``model_ms``, ``model_share``), and the step without them (``step_without_model_ms``): the ceiling
of every lever that cuts the model's time, as a ratio ``ratio_rel30_over_without_model``.

Model calls (``model_calls``, ``bench/model_calls.py``): the same model's rollout at H = ``--horizon`` from
mid-episode, at each batch of ``--model-batches`` (1, 10, 40), against its arithmetic floor (its matmul FLOPs at
the measured throughput of one ``torch.mm`` at the step's largest matmul shape), with the value output and the
advance at that batch, and the fit of a generated step's time against the batch (its fixed per-call part); beside
them the fused decode's (``decoder="fused"``, ``ttompc.policy.fused``) rollout, per generated step, per call, its
share of the same arithmetic floor and advance, whatever ``--mpc decoder`` the closed loop ran (``--mpc
decoder=fused`` runs the TTO methods' rollouts and advances fused: the ``rollout`` and ``observe`` parts then time
it).

Ends with one JSON line, also written to bench/results/step_profile.json (not with ``--quick``: 1 problem, 4 steps,
2 warm-up steps, 3 repetitions of each model call), with the machine record (``bench/record.py``). Absolute times
need a quiet machine; the ratios and shares are the figures to compare.
"""

from __future__ import annotations

import argparse
import functools
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from model_calls import model_calls, print_calls
from record import Machine, result_path, write_result
from timed_regions import Profiler

import ttompc.mpc.providers as providers_mod
import ttompc.solvers.engine as engine_mod
from ttompc.evaluation.closed_loop import ClosedLoopConfig, tasks
from ttompc.evaluation.problems import EvalProblem, eval_problem
from ttompc.mpc.loop import Episode, MPCController, MPCRun, run_mpc_batch
from ttompc.mpc.methods import MethodInputs, methods_for
from ttompc.mpc.providers import Provider, RELProvider, RemainingREL, full_horizon_plan
from ttompc.mpc.terminal import TargetFilter
from ttompc.mpc.tto import TTOProvider
from ttompc.policy import Planner
from ttompc.policy.rollout import RolloutContext
from ttompc.scenarios import Scenario, get_scenario

SCENARIOS = ("freeflyer", "quadrotor", "rpod")
# the shipped model of each scenario's headline, and the role ``ttompc evaluate mpc`` gives it (its method names)
MODELS = {"freeflyer": "freeflyer-ft-tto-v5", "quadrotor": "quadrotor-ft-tto-v6", "rpod": "rpod-ft-tto-v4"}
BASELINE = "REL-MPC"
PARTS = (
    "rollout",
    "conditioning",
    "terminal",
    "rel_warm_start",
    "scp_setup",
    "scp_solve",
    "scp_bookkeeping",
    "overhead",
    "observe",
)
MODEL_REGIONS = ("rollout", "value", "advance")  # the model's calls in a step (none nests in another)


def role(source: str) -> str:
    """``FT-TTO`` for a fine-tuned model (its name says ``ft``), else ``TTO``: the key ``ttompc evaluate mpc`` gives
    ``--ft-model`` and ``--model``, from which the method names follow (FT-TTO-MPC, R-FT-TTO-MPC, ...)."""
    return "FT-TTO" if "ft" in Path(source).name.lower().split("-") else "TTO"


# --------------------------------------------------------------------------------------------------- instrumentation
def part_of(path: str) -> str | None:
    """The part (``PARTS``) a step's region counts in, by its path: the plan's regions (``step/...``) and the observe
    after it (``observe/...``); None for a path outside both."""
    names = path.split("/")
    if names[0] == "observe":
        return "observe"
    if names[0] != "step":
        return None
    inner = names[1:]
    for name, part in (
        ("rollout", "rollout"),
        ("conditioning", "conditioning"),
        ("value", "conditioning"),
        ("terminal", "terminal"),
    ):
        if name in inner:
            return part
    if inner[:1] == ["warm_start"] and "rel" in inner:
        return "rel_warm_start"
    if inner[:1] == ["scp"]:
        return {"linearise": "scp_setup", "subproblem": "scp_solve"}.get(
            inner[1] if len(inner) > 1 else "", "scp_bookkeeping"
        )
    return "overhead"  # the step itself, the provider's warm start outside the parts above


class _TimedSolver:
    """A cached subproblem solver whose ``solve`` is a timed region; everything else passes through."""

    def __init__(self, inner: Any, solve: Callable[..., Any]) -> None:
        self._inner, self.solve = inner, solve

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


@contextmanager
def instrumented(prof: Profiler, scenario: Scenario) -> Iterator[None]:
    """The library functions a step runs, wrapped with ``prof``'s timers, for the duration of the block."""
    undo: list[tuple[Any, str, bool, Any]] = []

    def patch(obj: Any, name: str, make: Callable[[Any], Any]) -> None:
        if not hasattr(obj, name):  # the library changed under the bench: say where
            raise AttributeError(f"step_profile: {getattr(obj, '__name__', obj)!r} has no {name!r} to time")
        own = name in vars(obj)
        old = vars(obj)[name] if own else getattr(obj, name)
        undo.append((obj, name, own, old))
        setattr(obj, name, make(getattr(obj, name)))

    def on_step(plan: Any, path: str) -> None:
        prof.count["reused"] += bool(plan.reused)
        prof.count["fallbacks"] += bool(plan.fallback)
        prof.iterations[int(plan.iterations)] += 1

    def on_scp(res: Any, path: str) -> None:
        prof.count[f"{path}:iterations"] += res.iterations
        prof.count[f"{path}:backend_reported"] += res.solver_time  # the backends' own timers (not uniform across them)
        prof.count[f"{path}:kernel"] += sum(h.solver_status.startswith("RICCATI") for h in res.history)

    def on_rel(res: Any, path: str) -> None:
        prof.count[f"{path}:iterations"] += res.iterations

    def timed_lookup(fn: Callable[..., Any]) -> Callable[..., Any]:
        lookup = prof.region("solver_lookup", fn)

        @functools.wraps(fn)
        def get(*args: Any, **kwargs: Any) -> Any:
            solver = lookup(*args, **kwargs)
            return _TimedSolver(solver, prof.region("subproblem", solver.solve)) if prof.on else solver

        return get

    try:
        patch(MPCController, "plan", lambda f: prof.region("step", f, on_step))
        patch(MPCController, "solve", lambda f: prof.region("scp", f, on_scp))
        patch(TTOProvider, "warm_start", lambda f: prof.region("warm_start", f))
        patch(RELProvider, "warm_start", lambda f: prof.region("warm_start", f))
        patch(RolloutContext, "rollout", lambda f: prof.region("rollout", f, sync=True))
        patch(TTOProvider, "conditioning", lambda f: prof.region("conditioning", f))
        patch(Planner, "cost_to_go", lambda f: prof.region("value", f, sync=True))
        patch(TargetFilter, "__call__", lambda f: prof.region("terminal", f))
        patch(providers_mod, "_terminal", lambda f: prof.region("terminal", f))
        patch(RemainingREL, "__call__", lambda f: prof.region("rel", f, on_rel))
        patch(engine_mod, "get_solver", timed_lookup)
        patch(scenario, "convex_model", lambda f: prof.region("linearise", f))
        patch(scenario, "constraints", lambda f: prof.region("linearise", f))
        patch(MPCController, "observe", lambda f: prof.region("observe", f))
        patch(RolloutContext, "advance", lambda f: prof.region("advance", f, sync=True))
        yield
    finally:
        for obj, name, own, old in reversed(undo):
            if own:
                setattr(obj, name, old)
            else:
                delattr(obj, name)


# ---------------------------------------------------------------------------------------------------------- runs
def method_providers(name: str, cfg: ClosedLoopConfig, plans: list[Any], models: dict[str, Planner]) -> list[Provider]:
    """Fresh providers of method ``name`` (as the report names it) for the problems of ``plans``, from its factory."""
    s = cfg.settings
    for method in methods_for(models, cfg.robust_blend):
        model = models.get(method.model or "")
        if method.label(s, model) == name:
            return method.providers(MethodInputs(s, plans, model, cfg.robust_blend, cfg.rtg_scale))
    raise KeyError(f"the evaluation has no method {name!r} under protocol {cfg.protocol!r}")


def run_method(
    sc: Scenario,
    eps: list[EvalProblem],
    plans: list[Any],
    name: str,
    cfg: ClosedLoopConfig,
    models: dict[str, Planner],
    horizon: int,
    batch: int,
    max_steps: int | None,
) -> list[Episode]:
    """The episodes of ``name`` on ``eps``, in lockstep tasks of ``batch`` problems (as ``run_problems`` runs them)."""
    out: list[Episode] = []
    for chunk in tasks(len(eps), batch):
        sub = [eps[i] for i in chunk]
        out += run_mpc_batch(
            sc,
            [ep.start for ep in sub],
            method_providers(name, cfg, [plans[i] for i in chunk], models),
            MPCRun(horizon, cfg.settings, max_steps),
        )
    return out


def profile_row(prof: Profiler, episodes: list[Episode], horizon: int, protocol: str) -> dict[str, Any]:
    """Per-step means (ms) of the parts, their shares, iterations and the tree of regions; a step is its plan and
    the observe after it."""
    steps = sum(len(e.U) for e in episodes)
    for region in ("step", "observe"):
        if prof.calls[region] != steps:
            raise RuntimeError(f"timed {prof.calls[region]} calls of {region}, the episodes ran {steps} steps")
    ms = lambda seconds: 1e3 * seconds / steps  # noqa: E731  per episode-step
    step = prof.incl["step"] + prof.incl["observe"]
    model = sum(t for path, t in prof.incl.items() if path.rpartition("/")[2] in MODEL_REGIONS)
    selfs = prof.self_times()
    parts = dict.fromkeys(PARTS, 0.0)
    for path, t in selfs.items():
        if (part := part_of(path)) is not None:
            parts[part] += t
    scp_iters = prof.count["step/scp:iterations"]
    solved = steps - prof.count["reused"]
    sub_calls = prof.calls["step/scp/subproblem"]
    tree = {
        path: {"ms_per_step": ms(t), "self_ms_per_step": ms(selfs[path]), "calls_per_step": prof.calls[path] / steps}
        for path, t in sorted(prof.incl.items())
    }
    return {
        "horizon": horizon,
        "protocol": protocol,
        "episodes": len(episodes),
        "steps": steps,
        "mean_step_ms": ms(step),
        "plan_ms": ms(prof.incl["step"]),
        "loop_step_ms": 1e3 * float(np.mean(np.concatenate([e.step_times for e in episodes]))),
        "parts_ms": {k: ms(v) for k, v in parts.items()},
        "shares": {k: v / step for k, v in parts.items()},
        "scp_iterations_per_step": scp_iters / steps,
        "scp_iterations_per_solved_step": scp_iters / solved if solved else float("nan"),
        "iterations_histogram": {str(k): v for k, v in sorted(prof.iterations.items())},
        "subproblem_ms_per_call": 1e3 * prof.incl["step/scp/subproblem"] / sub_calls if sub_calls else float("nan"),
        "backend_reported_ms_per_call": (
            1e3 * prof.count["step/scp:backend_reported"] / sub_calls if sub_calls else float("nan")
        ),
        "linearise_ms_per_iteration": (
            1e3 * prof.incl["step/scp/linearise"] / scp_iters if scp_iters else float("nan")
        ),
        "rel_warm_start_iterations_per_step": prof.count["step/warm_start/rel:iterations"] / steps,
        "reused_steps": prof.count["reused"] / steps,
        "kernel_share": prof.count["step/scp:kernel"] / scp_iters if scp_iters else float("nan"),
        "fallbacks": prof.count["fallbacks"],
        "advance_ms": ms(prof.incl.get("observe/advance", 0.0)),
        "model_ms": ms(model),
        "model_share": model / step,
        "step_without_model_ms": ms(step - model),
        "cost": float(np.mean([e.cost for e in episodes])),
        "feasible": float(np.mean([e.feasible for e in episodes])),
        "tree": tree,
    }


def mpc_override(text: str) -> tuple[str, Any]:
    """``KEY=VALUE`` of ``--mpc`` as a (key, YAML value) pair, e.g. ``rti=true`` -> ("rti", True)."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key, yaml.safe_load(value)


def profile_scenario(name: str, source: str, args: argparse.Namespace) -> dict[str, Any]:
    sc = get_scenario(name)
    planner = Planner.from_pretrained(source, sc, device=args.device)
    models = {role(source): planner}
    tto_cfg = ClosedLoopConfig(
        scenario=name,
        protocol=args.protocol,
        mpc=dict(args.mpc),
        horizons=[args.horizon],
        batch=args.batch,
        workers=1,
        device=args.device,
    )
    rel_cfg = ClosedLoopConfig(
        scenario=name,
        protocol=args.rel_protocol,
        horizons=[args.rel_horizon],
        batch=args.batch,
        workers=1,
        device=args.device,
    )
    backend = tto_cfg.settings.backend
    t0 = time.perf_counter()
    eps = [eval_problem(sc, args.seed, i, nonconvex_only=True, backend=backend) for i in range(args.problems)]
    plans = [full_horizon_plan(sc, ep.problem, backend) for ep in eps]  # PLAN-ONCE/ORACLE's, as run_problems
    setup_s = time.perf_counter() - t0
    tto_names = [
        m.label(tto_cfg.settings, models[m.model])
        for m in methods_for(models, tto_cfg.robust_blend)
        if m.model is not None
    ]
    methods = [(BASELINE, rel_cfg, args.rel_horizon)] + [(m, tto_cfg, args.horizon) for m in tto_names]
    prof = Profiler(cuda=planner.device.type == "cuda")
    rows: dict[str, dict[str, Any]] = {}
    print(
        f"{name}: {source} ({sum(p.numel() for p in planner.model.parameters()) / 1e6:.2f}M params), "
        f"{len(eps)} problems, batch {args.batch}, setup {setup_s:.1f} s"
    )
    with instrumented(prof, sc):
        for method, cfg, H in methods:
            # warm-up outside the timing: one episode on problem 0 (every window shape's solver structure)
            run_method(sc, eps[:1], plans[:1], method, cfg, models, H, 1, args.warmup_steps)
            diff = None
            if args.verify:  # the same episodes untimed: the timers must not change what runs
                plain = run_method(sc, eps, plans, method, cfg, models, H, args.batch, args.max_steps)
            prof.reset()
            prof.on = True
            try:
                episodes = run_method(sc, eps, plans, method, cfg, models, H, args.batch, args.max_steps)
            finally:
                prof.on = False
            row = profile_row(prof, episodes, H, cfg.protocol)
            if args.verify:
                diff = max(float(np.max(np.abs(a.U - b.U), initial=0.0)) for a, b in zip(plain, episodes, strict=True))
                row["verify_max_control_difference"] = diff
                row["untimed_loop_step_ms"] = 1e3 * float(np.mean(np.concatenate([e.step_times for e in plain])))
            rows[f"{method}@{H}"] = row
    base = rows[f"{BASELINE}@{args.rel_horizon}"]["mean_step_ms"]
    learned = {k: r for k, r in rows.items() if not k.startswith(BASELINE + "@")}
    ratios = {k: base / r["mean_step_ms"] for k, r in learned.items()}
    ceilings = {k: base / r["step_without_model_ms"] for k, r in learned.items()}
    print_table(name, rows, ratios, ceilings)
    calls = model_calls(planner, [ep.problem for ep in eps], args.model_batches, args.horizon, args.model_reps)
    print_calls(name, calls)
    return {
        "model": source,
        "role": role(source),
        "params": sum(p.numel() for p in planner.model.parameters()),
        "problems": len(eps),
        "problem_indices": [ep.index for ep in eps],
        "batch": args.batch,
        "max_steps": args.max_steps,
        "settings": {"tto": asdict(tto_cfg.settings), "rel": asdict(rel_cfg.settings)},
        "methods": rows,
        f"ratio_rel{args.rel_horizon}_over": ratios,
        f"ratio_rel{args.rel_horizon}_over_without_model": ceilings,
        "model_calls": calls,
    }


def print_table(
    name: str, rows: dict[str, dict[str, Any]], ratios: dict[str, float], ceilings: dict[str, float]
) -> None:
    short = {
        "rollout": "roll",
        "conditioning": "cond",
        "terminal": "term",
        "rel_warm_start": "REL",
        "scp_setup": "setup",
        "scp_solve": "solve",
        "scp_bookkeeping": "scp-py",
        "overhead": "py",
        "observe": "obs",
    }
    head = " ".join(f"{short[p]:>6}" for p in PARTS)
    print(f"{'method':>28} {'step ms':>8} {head} {'model':>6} {'it/step':>7} {'sub ms':>6} {'ratio':>6} {'ceil':>6}")
    for key, r in rows.items():
        shares = " ".join(f"{100 * r['shares'][p]:>5.1f}%" for p in PARTS)
        ratio, ceil = (f"{x[key]:>5.2f}x" if key in x else f"{'':>6}" for x in (ratios, ceilings))
        print(
            f"{key:>28} {r['mean_step_ms']:>8.2f} {shares} {100 * r['model_share']:>5.1f}% "
            f"{r['scp_iterations_per_step']:>7.2f} {r['subproblem_ms_per_call']:>6.2f} {ratio} {ceil}"
        )
    print(
        f"  ({name}: shares of the mean step, the model's calls among them; ratio = {BASELINE}@30 mean step / the "
        "method's; ceil = the same over the method's step without its model time)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", action="append", choices=SCENARIOS, help="repeatable; default: all three")
    ap.add_argument("--model", action="append", default=[], help="SCENARIO=SOURCE replacing the shipped model")
    ap.add_argument("--problems", type=int, default=10)
    ap.add_argument("--seed", type=int, default=4242, help="root seed of the held-out problems")
    ap.add_argument("--horizon", type=int, default=10, help="H of the TTO methods")
    ap.add_argument("--rel-horizon", type=int, default=30, help="H of REL-MPC")
    ap.add_argument("--protocol", default="recommended", help="protocol of the TTO methods")
    ap.add_argument("--rel-protocol", default="paper", help="protocol of REL-MPC")
    ap.add_argument(
        "--mpc",
        action="append",
        default=[],
        type=mpc_override,
        metavar="KEY=VALUE",
        help="repeatable: an MPC setting over the TTO methods' protocol, e.g. --mpc rti=true",
    )
    ap.add_argument("--batch", type=int, default=ClosedLoopConfig.batch, help="problems in lockstep (evaluate's)")
    ap.add_argument("--max-steps", type=int, default=None, help="MPC steps per episode (default: all N)")
    ap.add_argument("--warmup-steps", type=int, default=None, help="steps of the warm-up episode (default: all N)")
    ap.add_argument("--verify", action="store_true", help="rerun untimed and check the controls are identical")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--model-batches", type=int, nargs="+", default=[1, 10, 40], help="batches of the model calls")
    ap.add_argument("--model-reps", type=int, default=20, help="timed repetitions of each model call")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: 1 problem, 4 steps, --verify, 3 model-call reps, no result file",
    )
    ap.add_argument("--out", default=str(result_path("step_profile")))
    args = ap.parse_args()
    if args.quick:
        args.problems, args.max_steps, args.warmup_steps, args.verify, args.model_reps = 1, 4, 2, True, 3
    scenarios = args.scenario or list(SCENARIOS)
    sources = dict(MODELS)
    for item in args.model:
        key, sep, src = item.partition("=")
        if not sep or key not in SCENARIOS:
            ap.error(f"--model takes SCENARIO=SOURCE with SCENARIO in {list(SCENARIOS)}, got {item!r}")
        sources[key] = src
    torch.set_num_threads(args.threads)
    machine = Machine()
    results = {name: profile_scenario(name, sources[name], args) for name in scenarios}
    summary = {
        "bench": "step_profile",
        "scenarios": results,
        "problems": args.problems,
        "seed": args.seed,
        "horizon": args.horizon,
        "rel_horizon": args.rel_horizon,
        "batch": args.batch,
        "max_steps": args.max_steps,
        "device": args.device,
        **machine.record(),
    }
    write_result(summary, None if args.quick else args.out)


if __name__ == "__main__":
    main()
