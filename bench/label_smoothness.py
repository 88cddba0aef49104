"""Are the expert's labels smooth in the state? (issue 57, item 2: the model can only fit labels that are.)

On held-out problems (the evaluation stream's non-convex ones), x* the problem's open-loop optimum
(``full_horizon_plan``): at each step t of ``--steps``, ``--draws`` starts x*_t + δ with δ ~ N(0, σ²) per component
in units of the scenario's ``state_scale``; DAgger's expert (``ttompc.mpc.expert``: REL, then SCP over [t, N)
from the start, under the protocol's settings) plans from each, and the plans are compared pairwise at t + 10:
ratio = ‖(X_i − X_j)_{t+10} / scale‖₂ / ‖(δ_i − δ_j) / scale‖₂. A smooth label map gives ratios near one value; a
switch of side around a keep-out zone gives one far above the median. Per σ: the pairs, the median and largest
ratio, the share of pairs over 5× the median, and the starts whose expert solve fell back (left out; a start inside
a keep-out zone is not told apart).

    python bench/label_smoothness.py --scenario rpod --problems 5 --sigmas 0.05,0.2
    python bench/label_smoothness.py --scenario quadrotor --problems 2 --sigmas 0.05 --draws 3 --no-write  # smoke

Prints a table and one JSON line, also written to bench/results/label_smoothness_<scenario>.json.
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np
from record import Machine, result_path, write_result

from ttompc.evaluation.measurement import Measurement
from ttompc.evaluation.problems import EvalProblem
from ttompc.mpc.expert import Expert, ExpertRollout
from ttompc.mpc.loop import StepPlan
from ttompc.mpc.plant import PlantNoise
from ttompc.mpc.providers import full_horizon_plan
from ttompc.mpc.settings import MPCSettings
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Scenario

AHEAD = 10  # the plans are compared at t + AHEAD
OUTLIER = 5.0  # a pair over this many times the median ratio counts as a jump


def expert_plan(scenario: Scenario, ep: EvalProblem, t: int, x: np.ndarray, settings: MPCSettings) -> StepPlan:
    """DAgger's expert plan over [t, N) of ``ep``'s problem from the state ``x`` (a fresh expert: no earlier plan)."""
    N = ep.problem.n_steps
    labelled = np.arange(N) == t
    draws = (ep.index, ep.seed, ep.problem, ep.rel, N)
    rollout = ExpertRollout.start(scenario, draws, np.zeros(N, dtype=bool), labelled, PlantNoise(), settings)
    Expert(scenario, [rollout], None, settings.backend).before(t, [], [x])
    return rollout.plans[t]


def ratios(
    scenario: Scenario,
    ep: EvalProblem,
    X_star: np.ndarray,
    t: int,
    sigma: float,
    draws: int,
    settings: MPCSettings,
    seed: int,
) -> tuple[list[dict[str, Any]], int]:
    """The pairs (module doc) of ``draws`` starts about x*_t of ``ep`` (``X_star``: its optimum's states) at noise
    ``sigma`` — problem, t, ‖δ_i − δ_j‖ and ‖X_i − X_j‖ at t + 10 (scaled) and their ratio — and how many starts
    fell back."""
    scale = scenario.state_units()
    rng = np.random.default_rng([seed, ep.index, t, round(sigma * 1e6)])
    deltas, ends, failed = [], [], 0
    for _ in range(draws):
        delta = rng.normal(scale=sigma, size=scenario.state_dim) * scale
        plan = expert_plan(scenario, ep, t, X_star[t] + delta, settings)
        if plan.fallback:
            failed += 1
            continue
        deltas.append(delta / scale)
        ends.append(plan.X[AHEAD] / scale)
    out = []
    for i, j in itertools.combinations(range(len(ends)), 2):
        d, x = float(np.linalg.norm(deltas[i] - deltas[j])), float(np.linalg.norm(ends[i] - ends[j]))
        out.append({"problem": ep.index, "t": t, "delta": d, "plan": x, "ratio": x / d})
    return out, failed


def summary(pairs: Sequence[dict[str, Any]], failed: int, starts: int) -> dict[str, Any]:
    """Pairs, median and largest ratio, the share of pairs over ``OUTLIER``× the median (all, and per step t), the
    starts that fell back, and the ten largest pairs."""
    r = np.asarray([p["ratio"] for p in pairs], dtype=np.float64)
    med = float(np.median(r)) if len(r) else float("nan")
    over = float(np.mean(r > OUTLIER * med)) if len(r) else float("nan")
    by_t = {
        str(t): float(np.mean([p["ratio"] > OUTLIER * med for p in pairs if p["t"] == t]))
        for t in sorted({p["t"] for p in pairs})
    }
    return {
        "pairs": len(r),
        "median": med,
        "max": float(r.max()) if len(r) else float("nan"),
        "share_over_5x_median": over,
        "share_over_5x_median_by_t": by_t,
        "starts": starts,
        "fell_back": failed,
        "largest": sorted(pairs, key=lambda p: -p["ratio"])[:10],
    }


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default="rpod")
    p.add_argument("--problems", type=int, default=5)
    p.add_argument("--seed", type=int, default=1001, help="root seed of the held-out problems (and of the draws)")
    p.add_argument("--sigmas", default="0.05,0.2", help="comma-separated noise levels, in state_scale units")
    p.add_argument("--steps", default="20,40,60,75", help="comma-separated steps t")
    p.add_argument("--draws", type=int, default=5, help="starts per (problem, t, sigma)")
    p.add_argument("--protocol", default="recommended", help="the MPC settings of the expert's solves")
    p.add_argument("--no-write", action="store_true", help="print only (a smoke run)")
    a = p.parse_args(argv)
    machine = Machine()
    sc = get_scenario(a.scenario)
    m = Measurement(protocol=a.protocol, problems=a.problems, seed=a.seed)
    eps = m.problem_set(sc, progress="problems")
    steps = [int(s) for s in a.steps.split(",") if int(s) + AHEAD <= sc.n_steps]
    optima = [full_horizon_plan(sc, ep.problem, m.settings.backend)[0] for ep in eps]
    rows = []
    for sigma in (float(s) for s in a.sigmas.split(",")):
        pairs, failed = [], 0
        for (ep, X_star), t in itertools.product(zip(eps, optima, strict=True), steps):
            r, f = ratios(sc, ep, X_star, t, sigma, a.draws, m.settings, a.seed)
            pairs += r
            failed += f
        rows.append({"sigma": sigma, **summary(pairs, failed, len(eps) * len(steps) * a.draws)})
        s = rows[-1]
        over = 100 * s["share_over_5x_median"]
        print(
            f"sigma {sigma:g}: {s['pairs']} pairs, median {s['median']:.3g}x, max {s['max']:.3g}x, "
            f"{over:.1f}% over 5x the median, {failed}/{s['starts']} starts fell back"
        )
    result = {
        "scenario": sc.name,
        "problems": a.problems,
        "seed": a.seed,
        "steps": steps,
        "draws": a.draws,
        "protocol": a.protocol,
        "ahead": AHEAD,
        "rows": rows,
        "machine": machine.record(),
    }
    out = None if a.no_write else result_path(f"label_smoothness_{sc.name}")
    write_result(
        result, out, {"scenario": sc.name, "rows": [{k: v for k, v in r.items() if k != "largest"} for r in rows]}
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
