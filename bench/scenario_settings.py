"""What a scenario's settings do, measured on the worked example (examples/di2d.py): the numbers in
docs/scenarios.md.

1. Open loop (REL then SCP, ``solve_problem``) on the same seeded problems for the shipped settings and for one
   wrong setting at a time: the scales (``state_scale``/``control_scale``, with the default QP backend and the conic
   one) and each ``SCPSettings`` field. Per variant: REL failures, SCP successes, mean SCP iterations, mean time per
   problem, cost relative to the shipped settings (on problems both solve) and returned solutions that cross the
   keep-out zone.
2. Closed loop (soft-mode MPC, H = 10, nominal plant) on held-out non-convex problems: REL-MPC and DIST-MPC with the
   shipped ``MPCWeights`` and with one weight off at a time. Per variant: runs that reach the goal within
   ``terminal_tol`` without a keep-out violation, the mean terminal error and the cost above the REL lower bound.

    python bench/scenario_settings.py [--problems 20] [--mpc-problems 6]

Prints both tables as markdown, then one JSON line, also written to bench/results/scenario_settings.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np
from record import Machine, result_path, write_result

from ttompc.evaluation.problems import eval_problem
from ttompc.mpc import DISTProvider, RELProvider, run_mpc
from ttompc.scenarios import MPCWeights, Scenario, get_scenario
from ttompc.seeding import problem_seed
from ttompc.solvers import solve_problem

EXAMPLE = f"{Path(__file__).resolve().parents[1] / 'examples' / 'di2d.py'}:DoubleIntegrator2D"
RESULTS = result_path("scenario_settings")


def variant(base: type[Scenario], **attrs: Any) -> Scenario:
    """An unregistered instance of ``base`` with some class attributes replaced."""
    return type(f"{base.__name__}Variant", (base,), attrs)()


def open_loop_variants(base: type[Scenario]) -> dict[str, tuple[Scenario, str]]:
    """label -> (scenario, backend): the default backend (the Riccati kernel, PIQP on other QPs) and the conic chain
    (QOCO, Clarabel), which is where scaling was measured to matter for RPOD (docs/design.md)."""
    scp, sx, su = base.scp, base.state_scale, base.control_scale
    replace = dataclasses.replace
    unscaled = variant(base, state_scale=(), control_scale=())
    large = variant(base, state_scale=tuple(1e3 * s for s in sx), control_scale=tuple(1e3 * s for s in su))
    small = variant(base, state_scale=tuple(1e-3 * s for s in sx), control_scale=tuple(1e-3 * s for s in su))
    return {
        "shipped": (base(), "auto"),
        "no scales (all 1)": (unscaled, "auto"),
        "scales 1e3 too large": (large, "auto"),
        "scales 1e-3 too small": (small, "auto"),
        "conic backend, shipped": (base(), "conic"),
        "conic backend, no scales": (unscaled, "conic"),
        "conic backend, scales 1e3 too large": (large, "conic"),
        "conic backend, scales 1e-3 too small": (small, "conic"),
        "tr_start 0.05 (too small)": (variant(base, scp=replace(scp, tr_start=0.05)), "auto"),
        "tr_start 100 (too large)": (variant(base, scp=replace(scp, tr_start=100.0)), "auto"),
        "tr_end 0.5 (too loose)": (variant(base, scp=replace(scp, tr_end=0.5)), "auto"),
        "max_iters 4": (variant(base, scp=replace(scp, max_iters=4)), "auto"),
        "penalty 0.01 (too low)": (variant(base, scp=replace(scp, penalty=0.01)), "auto"),
        "penalty 1e7 (too high)": (variant(base, scp=replace(scp, penalty=1e7)), "auto"),
        "feas_tol 1e-10 (too tight)": (variant(base, scp=replace(scp, feas_tol=1e-10)), "auto"),
    }


def open_loop(variants: dict[str, tuple[Scenario, str]], n: int) -> list[dict[str, Any]]:
    shipped = variants["shipped"][0]
    problems = [shipped.sample(np.random.default_rng(problem_seed(0, i))) for i in range(n)]
    costs: dict[str, list[float]] = {}
    rows = []
    for label, (sc, backend) in variants.items():
        ok, iters, times, viol, cost, rel_failures = 0, [], [], 0, [], 0
        for p in problems:
            t0 = time.perf_counter()
            _, scp = solve_problem(sc, p, backend=backend)
            times.append(time.perf_counter() - t0)
            if scp is None:  # REL failed
                rel_failures += 1
                cost.append(np.nan)
                continue
            iters.append(scp.iterations)
            viol += int(np.sum(shipped.violations(p, scp.X)) > 0)
            ok += scp.success
            cost.append(scp.cost if scp.success else np.nan)
        costs[label] = cost
        rows.append(
            {
                "variant": label,
                "rel_failures": rel_failures,
                "scp_success": f"{ok}/{n}",
                "mean_scp_iterations": float(np.mean(iters)) if iters else None,
                "mean_time_s": float(np.mean(times)),
                "solutions_in_keepout": viol,
                "cost_vs_shipped_pct": _relative(cost, costs["shipped"]),
            }
        )
    return rows


def _relative(cost: list[float], ref: list[float]) -> float | None:
    """Mean cost difference in % of the reference, on problems both solved."""
    a, b = np.asarray(cost), np.asarray(ref)
    both = np.isfinite(a) & np.isfinite(b)
    return float(np.mean((a[both] - b[both]) / b[both]) * 100) if both.any() else None


def closed_loop(base: type[Scenario], n: int, horizon: int = 10) -> list[dict[str, Any]]:
    w = base.mpc
    replace = dataclasses.replace
    cases: list[tuple[str, Any, MPCWeights]] = [
        ("REL-MPC, shipped", RELProvider, w),
        ("REL-MPC, end 0.1 (too weak)", RELProvider, replace(w, end=0.1)),
        ("REL-MPC, target 0.3 (too weak)", RELProvider, replace(w, target=0.3)),
        ("REL-MPC, target 30 (too strong)", RELProvider, replace(w, target=30.0)),
        ("REL-MPC, fuel 100 (too strong)", RELProvider, replace(w, fuel=100.0)),
        ("DIST-MPC, shipped", DISTProvider, w),
        ("DIST-MPC, dist 0.1 (too weak)", DISTProvider, replace(w, dist=(0.1,) * base.state_dim)),
        ("DIST-MPC, dist 10 (too strong)", DISTProvider, replace(w, dist=(10.0,) * base.state_dim)),
    ]
    shipped = base()
    problems = [eval_problem(shipped, 0, i) for i in range(n)]
    rows = []
    for label, provider, weights in cases:
        sc = variant(base, mpc=weights)
        eps = [run_mpc(sc, ep.problem, provider(), horizon, rel_cost=ep.rel_cost) for ep in problems]
        feasible = [e for e in eps if e.feasible]
        rows.append(
            {
                "variant": label,
                "reached_goal": f"{len(feasible)}/{n}",
                "mean_terminal_error": float(np.mean([e.terminal_error for e in eps])),
                "cost_above_rel_pct": float(np.mean([(e.cost - e.rel_cost) / e.rel_cost * 100 for e in feasible]))
                if feasible
                else None,
                "mean_step_ms": float(np.mean([e.step_times.mean() for e in eps]) * 1e3),
            }
        )
    return rows


def markdown(rows: list[dict[str, Any]]) -> str:
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        cells = [f"{v:.3g}" if isinstance(v, float) else ("–" if v is None else str(v)) for v in r.values()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=20, help="open-loop problems per variant")
    parser.add_argument("--mpc-problems", type=int, default=6, help="closed-loop problems per variant")
    args = parser.parse_args()
    base = type(get_scenario(EXAMPLE))
    machine = Machine()
    ol = open_loop(open_loop_variants(base), args.problems)
    print(markdown(ol), flush=True)
    cl = closed_loop(base, args.mpc_problems)
    print()
    print(markdown(cl))
    record = machine.record()
    result = {
        "scenario": EXAMPLE.rpartition("/")[2],
        "open_loop": ol,
        "closed_loop": cl,
        "problems": args.problems,
        "mpc_problems": args.mpc_problems,
        "wall_s": record["wall_s"],
        "machine": record,
    }
    write_result(result, RESULTS)


if __name__ == "__main__":
    main()
