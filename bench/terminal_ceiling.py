"""The ceiling of a learned terminal cost-to-go (issue 45): TTO-MPC at H = 10 whose windows pay an *exact* local
cost-to-go of their end state, against the paper's terminal target, on the same problems.

The oracle value of a window ending at step k is the second-order model of the optimal cost-to-go J*(·, k) about
the full-horizon SCP optimum x*_k: J(x) = λ_kᵀδ + ½ δᵀ M_k δ, δ = x − x*_k, with λ_k the optimum's costate
(``SCPResult.costates``, ∂J*/∂x_k) and M_k the finishing metric Φᵀ W⁻¹ Φ of the dynamics linearised about x*_k over
the N − k steps left (W the controllability Gramian: the least ½Σ‖u‖² that undoes δ), without the paper's pull.
``--noise`` adds a relative gradient error: λ̃_k = λ_k + ε‖λ_k‖ξ/‖ξ‖, ξ Gaussian per problem and step (seed 0), so
Σ‖λ̃ − λ‖/Σ‖λ‖ = ε, the figure ``python -m ttompc.evaluation.value_error`` reports for a learned value. The model
only warm-starts the windows under the oracle value (its target is not used). Quadratic stage costs only (the
quadrotor): for fuel costs the Gramian metric is not the finishing cost's curvature.

    python bench/terminal_ceiling.py [--model quadrotor-ft-tto-v6] [--problems 20] [--seed 1001] [--noise 0,0.2,0.5]
    python bench/terminal_ceiling.py --quick    # 2 problems, 12 steps, noise 0 (a smoke run, no file)

Prints a table and one JSON line, also written to bench/results/terminal_ceiling.json: per variant its goals, mean
(J − J_REL)/J_REL and the paired difference against TTO-MPC and R-TTO-MPC with the paper's target.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

import numpy as np
from record import Machine, result_path, write_result

from ttompc.evaluation.episodes import episode_record
from ttompc.evaluation.measurement import Measurement
from ttompc.evaluation.problems import EvalProblem
from ttompc.evaluation.stats import Outcome, paired
from ttompc.mpc.loop import MPCRun, run_mpc_batch
from ttompc.mpc.methods import METHODS, MethodInputs
from ttompc.mpc.terminal import TargetFilter
from ttompc.parallel import single_torch_thread
from ttompc.policy import Planner
from ttompc.policy.value import ValueExpansion
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.results import SCPResult
from ttompc.solvers.scp import SCPProblem, TerminalCost, solve_scp

RESULTS = result_path("terminal_ceiling")


def finishing_metric(scenario: Scenario, problem: Problem, stop: int, x_ref: np.ndarray) -> np.ndarray:
    """M (n, n): ½ δᵀ M δ is the least Σ ½‖u_j‖² that undoes a deviation δ of the state at ``stop`` by step N,
    under the dynamics linearised about ``x_ref`` with zero control (W regularised by 1e-6·‖W‖₂ where the steps
    left cannot steer a direction)."""
    tau = problem.n_steps - stop
    n, m = scenario.state_dim, scenario.control_dim
    lin = scenario.convex_model(
        problem, Window(stop, tau, problem.n_steps), np.tile(x_ref, (tau + 1, 1)), np.zeros((tau, m))
    )
    phi, gram = np.eye(n), np.zeros((n, n))
    for A, B in zip(lin.A, lin.B, strict=True):
        phi, gram = A @ phi, A @ gram @ A.T + B @ B.T
    gram += 1e-6 * np.linalg.norm(gram, 2) * np.eye(n)
    M = phi.T @ np.linalg.solve(gram, phi)
    return 0.5 * (M + M.T)


class LocalValue:
    """J(x) = λᵀ(x − c) + ½ (x − c)ᵀ M (x − c): a ``TerminalValue`` that is its own local model."""

    def __init__(self, center: np.ndarray, slope: np.ndarray, M: np.ndarray) -> None:
        self.center, self.slope, self.M = center, slope, M

    def expand(self, x: np.ndarray) -> ValueExpansion:
        d = np.asarray(x, dtype=np.float64) - self.center
        return ValueExpansion(float(self.slope @ d + 0.5 * d @ self.M @ d), self.slope + self.M @ d, self.M)

    def __call__(self, x: np.ndarray) -> float:
        return self.expand(x).value


class OracleValue(TargetFilter):
    """Each window that stops before N pays the oracle value about the optimum (module doc) and no target pull."""

    def __init__(self, optimum: SCPResult, slopes: np.ndarray) -> None:
        super().__init__()
        self.optimum, self.slopes = optimum, slopes

    def reset(self, scenario: Scenario, problem: Problem) -> None:
        super().reset(scenario, problem)
        self.problem = problem

    def __call__(self, scenario: Scenario, window: Window, X: np.ndarray) -> TerminalCost | None:
        if window.reaches_end:
            return None
        k, xs = window.stop, self.optimum.X[window.stop]
        M = finishing_metric(scenario, self.problem, k, xs)
        return TerminalCost(xs, 0.0, value=LocalValue(xs, self.slopes[k], M))


def noisy(costates: np.ndarray, eps: float, rng: np.random.Generator) -> np.ndarray:
    """λ + ε‖λ‖ξ/‖ξ‖ per step (the module doc's gradient error ε)."""
    xi = rng.normal(size=costates.shape)
    xi *= np.linalg.norm(costates, axis=1, keepdims=True) / np.maximum(np.linalg.norm(xi, axis=1, keepdims=True), 1e-12)
    return costates + eps * xi


def run(
    planner: Planner, method: str, problems: Sequence[EvalProblem], mpc: MPCRun, oracles: list[OracleValue] | None
) -> dict[int, Outcome]:
    """``method`` (a model method of ``METHODS``) on ``problems`` in lockstep, its terminal term replaced by
    ``oracles`` where given -> each problem's outcome."""
    provs = METHODS[method].providers(MethodInputs(mpc.settings, [None] * len(problems), planner))
    for p, term in zip(provs, oracles or [], strict=False):
        p.target = term  # type: ignore[attr-defined]
    with single_torch_thread():
        episodes = run_mpc_batch(planner.scenario, [ep.start for ep in problems], provs, mpc)
    return {ep.index: Outcome.of(episode_record(e)) for ep, e in zip(problems, episodes, strict=True)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="quadrotor-ft-tto-v6")
    ap.add_argument("--problems", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1001)
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--protocol", default="recommended")
    ap.add_argument("--noise", default="0,0.2,0.5", help="relative gradient errors of the oracle value")
    ap.add_argument("--quick", action="store_true", help="2 problems, 12 steps, noise 0; writes no result file")
    ap.add_argument("--out", default=None, help="default: bench/results/terminal_ceiling.json (none with --quick)")
    args = ap.parse_args()
    noises = [0.0] if args.quick else [float(e) for e in args.noise.split(",")]
    machine = Machine()
    planner = Planner.from_pretrained(args.model)
    sc = planner.scenario
    if sc.cost_norm != "quad":
        raise SystemExit(f"terminal_ceiling: {sc.name} pays {sc.cost_norm!r}; the oracle's curvature needs 'quad'")
    m = Measurement(protocol=args.protocol, problems=2 if args.quick else args.problems, seed=args.seed,
                    horizons=[args.horizon], max_steps=12 if args.quick else None)  # fmt: skip
    problems = m.problem_set(sc)
    optima = [solve_scp(SCPProblem(sc, ep.problem), ep.rel.X, ep.rel.U) for ep in problems]
    [(_, mpc)] = m.runs(sc)
    base = {name: run(planner, name, problems, mpc, None) for name in ("TTO-MPC", "R-TTO-MPC")}
    rows: dict[str, Any] = {}

    def row(name: str, outcomes: dict[int, Outcome]) -> None:
        inc = np.array([o.rel_increment for o in outcomes.values() if o.feasible]) * 100
        rows[name] = {"goals": len(inc), "mean": float(np.mean(inc)) if len(inc) else None,
                      "se": float(np.std(inc, ddof=1) / np.sqrt(len(inc))) if len(inc) > 1 else None,
                      **{f"vs {b}": paired(base[b], outcomes, scale=100)["paired"] for b in base}}  # fmt: skip
        vs = "  ".join(
            f"vs {b}: {rows[name][f'vs {b}']['mean']:+.1f} ± {rows[name][f'vs {b}']['se']:.1f}" for b in base
        )
        print(f"{name:>28} {rows[name]['goals']:>3}/{len(problems)} {rows[name]['mean'] or float('nan'):>8.1f}%  {vs}")

    for name, outcomes in base.items():
        row(f"{name} (target)", outcomes)
    for eps in noises:
        rng = np.random.default_rng(0)
        oracles = [OracleValue(o, noisy(o.costates, eps, rng)) for o in optima]  # type: ignore[arg-type]
        row(f"TTO-MPC (oracle value, ε={eps:g})", run(planner, "TTO-MPC", problems, mpc, oracles))
    summary = {"bench": "terminal_ceiling", "model": args.model, "protocol": args.protocol, "seed": args.seed,
               "problems": len(problems), "horizon": args.horizon, "rows": rows, **machine.record()}  # fmt: skip
    write_result(summary, args.out or (None if args.quick else RESULTS), {"bench": "terminal_ceiling", "rows": rows})


if __name__ == "__main__":
    main()
