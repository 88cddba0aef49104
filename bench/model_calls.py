"""The model's calls in a TTO-MPC step, timed alone against their arithmetic (``bench/step_profile.py``'s
``model_calls``): how much of the model's time is fixed per call (dispatch) and how much is arithmetic.

From a mid-episode context (B episodes advanced ``t`` steps along the model's own plan, a KV cache of t steps), at
each batch B:

* ``rollout_ms``: ``RolloutContext.rollout(H)``, the median of ``reps`` calls, and ``ms_per_generated_step``;
* ``mflop_per_generated_step``: the rollout's matmul FLOPs per generated step (``torch.utils.flop_counter``; the
  attention over the cache is not counted, under 5% of a step at these sizes);
* ``mm_gflops``: the throughput of one ``torch.mm`` at the step's largest matmul, (B·T, d) × (d, hidden) of the MLP
  (T tokens per step, d the width), the median of ``reps``·20 calls; ``floor_ms``: the rollout's FLOPs at that
  throughput, the arithmetic floor of the call, and ``arithmetic_share`` = floor / measured;
* ``value_ms``: the value output of B states (``Planner.cost_to_go``, one call; None without a value output) and
  ``advance_ms``: the KV-cache extension by one executed step (``RolloutContext.advance``, the median of ``reps``
  successive extensions, so the cache grows by ``reps`` steps after the rollouts are timed).

The fused decode (``decoder="fused"``, ``ttompc.policy.fused``) from the same mid-episode context, where the model
and scenario allow it (else ``fused`` is None and ``fused_reason`` says why): ``fused.rollout_ms`` and
``ms_per_generated_step`` as above, ``call_ms`` its per-call part independent of H (the line through its H = 1 and
H-step rollouts: what a rollout costs besides its generated steps: the torch window maps, the weight check, numba's
dispatch), ``floor_share`` = the torch rollout's arithmetic floor / the fused rollout, ``speedup`` = torch rollout /
fused rollout, ``advance_ms`` (the fused KV-cache extension by a step no rollout started from: computed) and
``step_ms``: the model's part of one MPC step, as TTO-MPC makes its calls (the value output of the measured states
where the model has one, the rollout, then the advance by the plan's first step, which claims the rollout's token:
``ttompc.policy.fused``), the median of ``reps`` successive steps.

``fit``: the least-squares line through (B, ms per generated step): ``fixed_ms`` is the part of a generated step
that does not grow with the batch (the per-call overhead), ``ms_per_row`` what each episode adds; ``fused_fit`` the
same for the fused decode.

Alone (``python bench/model_calls.py``, one torch thread): the calls of ``--model`` (default the quadrotor's shipped
model) at ``--batches`` (default 1), or, with ``--random WIDTHxLAYERSxHEADS``, of a randomly initialised stacked
model of that size with the shipped model's scenario, statistics and value output (a larger model's cost before one
is trained); one JSON line, also written to bench/results/model_calls.json (``--out``).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from ttompc.policy import Planner, RolloutContext
from ttompc.policy.fused import fused_support
from ttompc.scenarios import Problem


def median_ms(fn: Callable[[], Any], reps: int) -> float:
    """The median wall time of ``reps`` calls of ``fn`` (ms), after one untimed call."""
    fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def mid_context(planner: Planner, problems: Sequence[Problem], t: int, decoder: str = "torch") -> RolloutContext:
    """The episodes of ``problems`` at step ``t``: conditioned on the data's mean rtg and advanced along the model's
    own t-step plan, so the KV cache holds t executed steps (decoding with ``decoder``)."""
    ctx = planner.context(problems, rtg0=float(planner.stats.mean["rtg"][0]), decoder=decoder)
    plan = ctx.rollout(t)
    for k in range(t):
        ctx.advance(plan.actions[:, k], plan.states[:, k + 1])
    return ctx


def mm_gflops(rows: int, width: int, hidden: int, dtype: torch.dtype, reps: int) -> float:
    """GFLOP/s of one ``torch.mm`` of (rows, width) × (width, hidden), the median of ``reps`` calls."""
    a, b = torch.randn(rows, width, dtype=dtype), torch.randn(width, hidden, dtype=dtype)
    return 2.0 * rows * width * hidden / (1e6 * median_ms(lambda: torch.mm(a, b), reps))


def advance_ms(ctx: RolloutContext, reps: int) -> float:
    """One KV-cache extension (``RolloutContext.advance`` along the model's plan), the median of ``reps``."""
    plan = ctx.rollout(reps + 1)
    steps = iter(range(reps + 1))

    def advance() -> None:
        k = next(steps)
        ctx.advance(plan.actions[:, k], plan.states[:, k + 1])

    return median_ms(advance, reps)


def fused_calls(
    planner: Planner, problems: Sequence[Problem], t: int, horizon: int, reps: int, torch_ms: float, floor_ms: float
) -> dict[str, Any]:
    """The fused decode's rollout and advance from step ``t`` (module doc), beside the torch rollout's time and
    arithmetic floor."""
    ctx = mid_context(planner, problems, t, decoder="fused")
    rollout_ms = median_ms(lambda: ctx.rollout(horizon), reps)
    one_ms = median_ms(lambda: ctx.rollout(1), reps)
    step_ms = (rollout_ms - one_ms) / (horizon - 1) if horizon > 1 else rollout_ms
    return {
        "rollout_ms": rollout_ms,
        "ms_per_generated_step": rollout_ms / horizon,
        "call_ms": rollout_ms - horizon * step_ms,
        "floor_share": floor_ms / rollout_ms,
        "speedup": torch_ms / rollout_ms,
        "advance_ms": advance_ms(ctx, reps),
        "step_ms": mpc_step_ms(planner, problems, t, horizon, reps),
    }


def mpc_step_ms(planner: Planner, problems: Sequence[Problem], t: int, horizon: int, reps: int) -> float:
    """The model's calls of one fused MPC step from step ``t`` on (module doc: ``step_ms``), the median of ``reps``."""
    ctx = mid_context(planner, problems, t, decoder="fused")
    plan = ctx.rollout(reps + 2)  # the executed steps
    steps = iter(range(reps + 1))
    X = np.stack([p.x0 for p in problems])

    def step() -> None:
        k = next(steps)
        if planner.has_value:
            planner.cost_to_go(problems, X, t + k)
        ctx.rollout(horizon)
        ctx.advance(plan.actions[:, k], plan.states[:, k + 1])

    return median_ms(step, reps)


def batch_calls(planner: Planner, problems: Sequence[Problem], t: int, horizon: int, reps: int) -> dict[str, Any]:
    """The model's calls at the batch of ``problems`` from step ``t`` (module doc)."""
    model = planner.model
    ctx = mid_context(planner, problems, t)
    rollout_ms = median_ms(lambda: ctx.rollout(horizon), reps)
    with FlopCounterMode(display=False) as counter:
        ctx.rollout(horizon)
    flops = float(counter.get_total_flops())
    width, hidden = model.cfg.n_embd, model.cfg.mlp_ratio * model.cfg.n_embd
    rows = len(problems) * model.cfg.tokens_per_step
    gflops = mm_gflops(rows, width, hidden, next(model.parameters()).dtype, 20 * reps)
    floor_ms = flops / (1e6 * gflops)
    X = np.stack([p.x0 for p in problems])
    value_ms = median_ms(lambda: planner.cost_to_go(problems, X, t), reps) if planner.has_value else None
    can_fuse = fused_support(model, planner.scenario.batched_model(problems)) is None
    fused = fused_calls(planner, problems, t, horizon, reps, rollout_ms, floor_ms) if can_fuse else None
    return {
        "rollout_ms": rollout_ms,
        "ms_per_generated_step": rollout_ms / horizon,
        "mflop_per_generated_step": flops / horizon / 1e6,
        "mm_gflops": gflops,
        "floor_ms": floor_ms,
        "arithmetic_share": floor_ms / rollout_ms,
        "value_ms": value_ms,
        "advance_ms": advance_ms(ctx, reps),
        "fused": fused,
    }


def model_calls(
    planner: Planner, problems: Sequence[Problem], batches: Sequence[int], horizon: int, reps: int
) -> dict[str, Any]:
    """The model's calls at each batch in ``batches`` (the problems cycled to fill it) from mid-episode, H =
    ``horizon``, and the fit of a generated step's time against the batch (module doc)."""
    N = problems[0].n_steps
    t = min(N // 2, planner.model.cfg.max_steps - horizon - reps - 1)
    cycled = lambda B: [problems[i % len(problems)] for i in range(B)]  # noqa: E731
    rows = {str(B): batch_calls(planner, cycled(B), t, horizon, reps) for B in batches}
    reason = fused_support(planner.model, planner.scenario.batched_model(problems[:1]))
    out: dict[str, Any] = {"t": t, "horizon": horizon, "reps": reps, "batches": rows, "fused_reason": reason}
    if len(batches) > 1:
        out["fit"] = fit(batches, [r["ms_per_generated_step"] for r in rows.values()])
        if reason is None:
            out["fused_fit"] = fit(batches, [r["fused"]["ms_per_generated_step"] for r in rows.values()])
    return out


def fit(batches: Sequence[int], ms: Sequence[float]) -> dict[str, float]:
    """The least-squares line of ms per generated step against the batch: its intercept and slope."""
    slope, fixed = np.polyfit(np.asarray(batches, dtype=float), np.asarray(ms), 1)
    return {"fixed_ms": float(fixed), "ms_per_row": float(slope)}


def print_calls(name: str, calls: dict[str, Any]) -> None:
    """One line per batch: the rollout, per generated step, its arithmetic floor, the value and the advance."""
    print(f"  {name} model calls from t = {calls['t']}, H = {calls['horizon']}:")
    for B, r in calls["batches"].items():
        value = "-" if r["value_ms"] is None else f"{r['value_ms']:.3f}"
        print(f"    B={B:>3}: rollout {r['rollout_ms']:7.3f} ms ({r['ms_per_generated_step']:.3f} ms per step), "
              f"arithmetic floor {r['floor_ms']:.3f} ms ({r['mflop_per_generated_step']:.1f} MFLOP per step at "
              f"{r['mm_gflops']:.1f} GFLOP/s: {100 * r['arithmetic_share']:.0f}% of it); value {value} ms; advance "
              f"{r['advance_ms']:.3f} ms")  # fmt: skip
        f = r["fused"]
        if f is not None:
            print(f"           fused: rollout {f['rollout_ms']:7.3f} ms ({f['ms_per_generated_step']:.3f} ms per step, "
                  f"{f['call_ms']:.3f} ms per call; floor {100 * f['floor_share']:.0f}% of it; {f['speedup']:.2f}x "
                  f"the torch rollout); advance {f['advance_ms']:.3f} ms; MPC step's model calls "
                  f"{f['step_ms']:.3f} ms")  # fmt: skip
    if calls["fused_reason"] is not None:
        print(f"    no fused decode: {calls['fused_reason']}")
    for key, label in (("fit", "torch"), ("fused_fit", "fused")):
        if key in calls:
            line = calls[key]
            print(f"    {label}: per generated step = {line['fixed_ms']:.3f} ms fixed + {line['ms_per_row']:.4f} ms "
                  "per episode")  # fmt: skip


def random_planner(shipped: Planner, size: str) -> Planner:
    """A randomly initialised stacked model of ``size`` = "WIDTHxLAYERSxHEADS" (seed 0) with ``shipped``'s
    scenario, statistics and value output; raises ``ValueError`` for a malformed size."""
    from dataclasses import replace

    from ttompc.policy.gpt import TrajectoryGPT

    try:
        width, layers, heads = (int(x) for x in size.split("x"))
    except ValueError:
        raise ValueError(f"--random must be WIDTHxLAYERSxHEADS, e.g. 192x4x6, got {size!r}") from None
    cfg = replace(shipped.model.cfg, n_embd=width, n_layer=layers, n_head=heads, layout="stacked")
    torch.manual_seed(0)
    return Planner(TrajectoryGPT(cfg).eval(), shipped.scenario, shipped.stats)


def main() -> None:
    import argparse

    from record import Machine, result_path, write_result

    from ttompc.evaluation.problems import eval_problem

    p = argparse.ArgumentParser(description="The model's calls of a TTO-MPC step, alone (module doc).")
    p.add_argument("--model", default="quadrotor-ft-tto-v6", help="zoo name or bundle (default quadrotor-ft-tto-v6)")
    p.add_argument("--random", default=None, help="WIDTHxLAYERSxHEADS: a random model of that size instead")
    p.add_argument("--batches", type=int, nargs="+", default=[1])
    p.add_argument("--horizon", type=int, default=10)
    p.add_argument("--reps", type=int, default=30)
    p.add_argument("--seed", type=int, default=4242, help="root seed of the evaluation problems")
    p.add_argument("--out", default=str(result_path("model_calls")))
    args = p.parse_args()
    torch.set_num_threads(1)
    machine = Machine()
    planner = Planner.from_pretrained(args.model)
    if args.random:
        planner = random_planner(planner, args.random)
    problems = [eval_problem(planner.scenario, args.seed, i).problem for i in range(max(args.batches))]
    cfg = planner.model.cfg
    name = f"{args.random or args.model} ({planner.model.num_parameters() / 1e6:.2f}M, {cfg.n_embd}x{cfg.n_layer})"
    calls = model_calls(planner, problems, args.batches, args.horizon, args.reps)
    print_calls(name, calls)
    result = {"bench": "model_calls", "model": name, "calls": calls, "machine": machine.record()}
    line = {B: {"rollout_ms": round(r["fused"]["rollout_ms"], 3), "step_ms": round(r["fused"]["step_ms"], 3)}
            for B, r in calls["batches"].items() if r["fused"]}  # fmt: skip
    write_result(result, args.out, {"bench": "model_calls", "model": name, "fused": line})


if __name__ == "__main__":
    main()
