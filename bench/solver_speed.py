"""SCP engine speed and robustness, measured against baselines in the same run.

1. Speed (per scenario, the same seeded problems): our engine (structure built once, values updated, QOCO/Clarabel)
   vs the naive baseline that rebuilds a cvxpy problem from per-timestep constraint lists every iteration (the
   reference's approach, Clarabel behind cvxpy). Reports time per SCP iteration, per whole REL+SCP solve, the raw
   convex-solver share of our time, and the relative cost difference of the two (same subproblems, same optima).
2. Robustness (free-flyer, 200 seeded problems): failure rate of the penalized (SCvx-style) formulation vs the
   reference formulation (hard linearised constraints), and their costs where both succeed.
3. Quadrotor: OSQP (∞-norm trust region, a QP) vs the conic path (2-norm trust region) — time, cost, iterations.

Ends with one JSON line of headline figures, also written to bench/results/solver_speed.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from ttompc.scenarios import get_scenario, list_scenarios
from ttompc.solvers import solve_problem
from ttompc.solvers.engine import backend_chain


def run_set(scenario, seeds, **kw) -> dict:
    tot, its, solver, costs, ok = [], [], [], [], []
    for seed in seeds:
        p = scenario.sample(np.random.default_rng(seed))
        t0 = time.perf_counter()
        rel, scp = solve_problem(scenario, p, **kw)
        tot.append(time.perf_counter() - t0)
        its.append(rel.iterations + (scp.iterations if scp else 0))
        solver.append(rel.solver_time + (scp.solver_time if scp else 0.0))
        costs.append(scp.cost if scp is not None and scp.success else np.nan)
        ok.append(bool(scp is not None and scp.success))
    tot, its, solver = np.array(tot), np.array(its), np.array(solver)
    return {
        "per_iter_s": float(tot.sum() / its.sum()),
        "solve_median_s": float(np.median(tot)),
        "solve_mean_s": float(tot.mean()),
        "raw_solver_per_iter_s": float(solver.sum() / its.sum()),
        "mean_iterations": float(its.mean()),
        "success_rate": float(np.mean(ok)),
        "costs": costs,
    }


def speed(name: str, n_problems: int, n_naive: int) -> dict:
    scenario = get_scenario(name)
    seeds = list(range(n_problems))
    run_set(scenario, seeds[:1])  # warm the structure cache and imports outside the timing
    ours = run_set(scenario, seeds)
    naive = run_set(scenario, seeds[:n_naive], backend="cvxpy-naive")
    c_ours, c_naive = np.array(ours.pop("costs")[:n_naive]), np.array(naive.pop("costs"))
    both = np.isfinite(c_ours) & np.isfinite(c_naive)
    rel_diff = float(np.max(np.abs(c_ours[both] - c_naive[both]) / np.abs(c_naive[both]))) if both.any() else None
    row = {
        "scenario": name,
        "backend": "+".join(backend_chain("auto", scenario)),
        "ours": ours,
        "naive": naive,
        "speedup_per_iter": naive["per_iter_s"] / ours["per_iter_s"],
        "overhead_vs_raw_solver": ours["per_iter_s"] / ours["raw_solver_per_iter_s"],
        "max_rel_cost_diff": rel_diff,
    }
    print(
        f"[{name}] ours {ours['per_iter_s'] * 1e3:.1f} ms/iter (raw solver {ours['raw_solver_per_iter_s'] * 1e3:.1f}"
        f" ms, x{row['overhead_vs_raw_solver']:.2f}), solve median {ours['solve_median_s']:.3f} s | naive "
        f"{naive['per_iter_s'] * 1e3:.0f} ms/iter, solve {naive['solve_mean_s']:.2f} s | speed-up "
        f"x{row['speedup_per_iter']:.1f} | max rel cost diff {rel_diff}",
        flush=True,
    )
    return row


def robustness(n: int) -> dict:
    scenario = get_scenario("freeflyer")
    out = {}
    for form in ("penalized", "reference"):
        costs, fails = [], []
        for seed in range(n):
            p = scenario.sample(np.random.default_rng(seed))
            _, scp = solve_problem(scenario, p, formulation=form)
            good = scp is not None and scp.success
            costs.append(scp.cost if good else np.nan)
            if not good:
                fails.append(seed)
        out[form] = {
            "failures": len(fails),
            "failure_rate": len(fails) / n,
            "failed_seeds": fails,
            "costs": np.array(costs),
        }
    a, b = out["penalized"].pop("costs"), out["reference"].pop("costs")
    both = np.isfinite(a) & np.isfinite(b)
    out["both_succeed"] = int(both.sum())
    out["max_rel_cost_excess_vs_reference"] = float(np.max((a[both] - b[both]) / b[both])) if both.any() else None
    print(
        f"[robustness, freeflyer, {n} problems] failures: penalized {out['penalized']['failures']}, reference "
        f"{out['reference']['failures']}; where both succeed ({out['both_succeed']}) max relative cost excess of "
        f"penalized over reference {out['max_rel_cost_excess_vs_reference']}",
        flush=True,
    )
    return out


def quadrotor_paths(n: int) -> dict:
    scenario = get_scenario("quadrotor")
    seeds = list(range(n))
    rows = {}
    for label, kw in {
        "osqp-linf": {"backend": "osqp"},
        "piqp-linf": {"backend": "piqp"},
        "conic-l2": {"backend": "auto"},
        "conic-linf": {"backend": "auto", "trust_norm": "linf"},
    }.items():
        run_set(scenario, seeds[:1], **kw)
        r = run_set(scenario, seeds, **kw)
        costs = np.array(r.pop("costs"))
        r["mean_cost"] = float(np.nanmean(costs)) if np.isfinite(costs).any() else None
        rows[label] = r
        print(
            f"[quadrotor {label}] {r['per_iter_s'] * 1e3:.1f} ms/iter, solve median {r['solve_median_s']:.3f} s, "
            f"iters {r['mean_iterations']:.1f}, mean cost {r['mean_cost']}, success {r['success_rate']:.2f}",
            flush=True,
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", type=int, default=20)
    ap.add_argument("--naive-problems", type=int, default=20, help="problems for the (slow) naive baseline")
    ap.add_argument("--robustness", type=int, default=200)
    ap.add_argument("--only", choices=["speed", "robustness", "quadrotor"], help="run one part (merged into --out)")
    ap.add_argument("--scenarios", default=",".join(list_scenarios()))
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "solver_speed.json"))
    args = ap.parse_args()
    machine = {"platform": platform.platform(), "processor": platform.processor(), "python": platform.python_version()}
    out = Path(args.out)
    # --only re-runs one part and keeps the others from the previous result file
    result: dict = json.loads(out.read_text()) if args.only and out.is_file() else {"speed": {}}
    result["machine"] = machine
    scenarios = args.scenarios.split(",")
    if args.only in (None, "speed"):
        for name in scenarios:
            n_naive = args.naive_problems if name == "freeflyer" else min(args.naive_problems, 5)
            result["speed"][name] = speed(
                name, args.problems if name == "freeflyer" else min(args.problems, 10), n_naive
            )
    if args.only in (None, "robustness") and args.robustness:
        result["robustness"] = robustness(args.robustness)
    if args.only in (None, "quadrotor") and "quadrotor" in scenarios:
        result["quadrotor_paths"] = quadrotor_paths(min(args.problems, 10))
    ff = result["speed"].get("freeflyer", {})
    headline = {
        "ff_per_iter_ms": ff.get("ours", {}).get("per_iter_s", np.nan) * 1e3,
        "ff_solve_median_s": ff.get("ours", {}).get("solve_median_s"),
        "ff_speedup_vs_naive": ff.get("speedup_per_iter"),
        "ff_overhead_vs_raw_solver": ff.get("overhead_vs_raw_solver"),
        "ff_max_rel_cost_diff": ff.get("max_rel_cost_diff"),
        "ff_failure_rate": result.get("robustness", {}).get("penalized", {}).get("failure_rate"),
        "ff_reference_failure_rate": result.get("robustness", {}).get("reference", {}).get("failure_rate"),
        **{f"{k}_speedup_vs_naive": v["speedup_per_iter"] for k, v in result["speed"].items() if k != "freeflyer"},
    }
    result["headline"] = headline
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=float))
    print(json.dumps(headline, default=float))


if __name__ == "__main__":
    main()
