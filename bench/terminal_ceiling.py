"""The ceiling of a learned terminal cost-to-go (issue 45): TTO-MPC at H = 10 whose windows pay an *exact* local
cost-to-go of their end state, against the paper's terminal target, on the same problems.

The oracle value of a window ending at step k is the second-order model of the optimal cost-to-go J*(·, k) about
the full-horizon SCP optimum x*_k: J(x) = λ_kᵀδ + ½ δᵀ M_k δ, δ = x − x*_k, without the paper's pull (``CostToGo``):

* ``--curvature gramian`` (the default for a quadratic stage cost, the quadrotor): λ_k the optimum's costate
  (``SCPResult.costates``, ∂J*/∂x_k) and M_k the finishing metric Φᵀ W⁻¹ Φ of the dynamics linearised about x*_k
  over the N − k steps left (W the controllability Gramian: the least ½Σ‖u‖² that undoes δ);
* ``--curvature differences`` (the default for a fuel cost, RPOD, whose cost-to-go the Gramian does not model):
  ∇J*(x, k) = A_kᵀ λ_{k+1}(x), the costate of x_{k+1} in the solve of [k, N) from x (no constraint touches its fixed
  start), so λ_k is that at x*_k and M_k the positive part of its central differences (steps of 1e-3 of each state
  unit; 2n + 1 solves of [k, N) per step k, on the scenario's path). Where J* has a kink (the 2-norm fuel's
  cost-to-go has them) the differences give a stiff M_k, about the jump of λ over the step.

``--noise`` adds a relative gradient error: λ̃_k = λ_k + ε‖λ_k‖ξ/‖ξ‖, ξ Gaussian per problem and step (seed 0), so
Σ‖λ̃ − λ‖/Σ‖λ‖ = ε, the figure ``python -m ttompc.evaluation.value_error`` reports for a learned value. The model
only warm-starts the windows under the oracle value (its target is not used).

    python bench/terminal_ceiling.py [--model quadrotor-ft-tto-v6] [--problems 20] [--seed 1001] [--noise 0,0.2,0.5]
    python bench/terminal_ceiling.py --model rpod-ft-tto-v4 --quick    # 2 problems, 12 steps, noise 0 (a smoke run)

Prints a table and one JSON line, also written to bench/results/terminal_ceiling.json (other scenarios than the
quadrotor: terminal_ceiling_<scenario>.json): per variant its goals, mean (J − J_REL)/J_REL and the paired difference
against TTO-MPC and R-TTO-MPC with the paper's target.
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

CURVATURES = ("gramian", "differences")


def results_file(scenario: str) -> str:
    """bench/results/terminal_ceiling.json for the quadrotor (the first measured), terminal_ceiling_<scenario>.json
    for the others."""
    return str(result_path("terminal_ceiling" if scenario == "quadrotor" else f"terminal_ceiling_{scenario}"))


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


class CostToGo:
    """One problem's local models (λ_k, M_k) of J*(·, k) about its full-horizon optimum under ``curvature`` (module
    doc), computed on first need and kept: the rows of every noise level share them."""

    def __init__(self, scenario: Scenario, problem: Problem, optimum: SCPResult, curvature: str) -> None:
        if optimum.costates is None:
            raise SystemExit(f"terminal_ceiling: the optimum of a {scenario.name} problem has no costates")
        self.scenario, self.problem, self.optimum, self.curvature = scenario, problem, optimum, curvature
        self._models: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(λ_k (n,), M_k (n, n)) for a window that stops at k < N."""
        if k not in self._models:
            self._models[k] = self._gramian(k) if self.curvature == "gramian" else self._differences(k)
        return self._models[k]

    def _gramian(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        opt = self.optimum
        assert opt.costates is not None  # checked in __init__
        return opt.costates[k], finishing_metric(self.scenario, self.problem, k, opt.X[k])

    def _differences(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        sc, p, opt = self.scenario, self.problem, self.optimum
        window = Window(k, p.n_steps - k, p.n_steps)
        A = sc.convex_model(p, window, opt.X[k:], opt.U[k:]).A[0]

        def slope(x: np.ndarray) -> np.ndarray | None:
            X0 = opt.X[k:].copy()
            X0[0] = x
            res = solve_scp(SCPProblem(sc, p, window), X0, opt.U[k:])
            return None if not res.success or res.costates is None else A.T @ res.costates[1]

        x, steps = opt.X[k], 1e-3 * sc.state_units()
        center = slope(x)
        if center is None:
            raise SystemExit(f"terminal_ceiling: the solve of [{k}, {p.n_steps}) from the optimum gave no costates")

        def column(e: np.ndarray, h: float) -> np.ndarray:
            """Central difference of the slope at x along e; one-sided where the goal is out of reach from one side
            (the perturbed start's solve is infeasible near N), none where from both."""
            plus, minus = slope(x + h * e), slope(x - h * e)
            if plus is not None and minus is not None:
                return (plus - minus) / (2 * h)
            if plus is not None:
                return (plus - center) / h
            if minus is not None:
                return (center - minus) / h
            return np.zeros_like(center)

        D = np.stack([column(e, h) for e, h in zip(np.eye(len(x)), steps, strict=True)], axis=1)
        w, V = np.linalg.eigh(0.5 * (D + D.T))
        return center, (V * np.maximum(w, 0.0)) @ V.T


class OracleValue(TargetFilter):
    """Each window that stops before N pays the oracle value about the optimum (module doc) and no target pull, its
    slope off by ``eps`` along the unit ``directions`` (N+1, n)."""

    def __init__(self, models: CostToGo, directions: np.ndarray, eps: float) -> None:
        super().__init__()
        self.models, self.directions, self.eps = models, directions, eps

    def __call__(self, scenario: Scenario, window: Window, X: np.ndarray) -> TerminalCost | None:
        if window.reaches_end:
            return None
        k, xs = window.stop, self.models.optimum.X[window.stop]
        slope, M = self.models(k)
        slope = slope + self.eps * np.linalg.norm(slope) * self.directions[k]
        return TerminalCost(xs, 0.0, value=LocalValue(xs, slope, M))


def directions(shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """ξ/‖ξ‖ per step, ξ Gaussian (the module doc's gradient error: λ + ε‖λ‖ξ/‖ξ‖)."""
    xi = rng.normal(size=shape)
    return xi / np.maximum(np.linalg.norm(xi, axis=1, keepdims=True), 1e-12)


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
    ap.add_argument(
        "--curvature",
        choices=CURVATURES,
        default=None,
        help="the oracle's M_k (module doc); default: gramian for a quadratic stage cost, else differences",
    )
    ap.add_argument("--quick", action="store_true", help="2 problems, 12 steps, noise 0; writes no result file")
    ap.add_argument("--out", default=None, help="default: ``results_file`` (none with --quick)")
    args = ap.parse_args()
    noises = [0.0] if args.quick else [float(e) for e in args.noise.split(",")]
    machine = Machine()
    planner = Planner.from_pretrained(args.model)
    sc = planner.scenario
    curvature = args.curvature or ("gramian" if sc.cost_norm == "quad" else "differences")
    m = Measurement(
        protocol=args.protocol,
        problems=2 if args.quick else args.problems,
        seed=args.seed,
        horizons=[args.horizon],
        max_steps=12 if args.quick else None,
    )
    problems = m.problem_set(sc)
    optima = [solve_scp(SCPProblem(sc, ep.problem), ep.rel.X, ep.rel.U) for ep in problems]
    models = [CostToGo(sc, ep.problem, o, curvature) for ep, o in zip(problems, optima, strict=True)]
    [(_, mpc)] = m.runs(sc)
    base = {name: run(planner, name, problems, mpc, None) for name in ("TTO-MPC", "R-TTO-MPC")}
    rows: dict[str, Any] = {}

    def row(name: str, outcomes: dict[int, Outcome]) -> None:
        inc = np.array([o.rel_increment for o in outcomes.values() if o.feasible]) * 100
        rows[name] = {
            "goals": len(inc),
            "mean": float(np.mean(inc)) if len(inc) else None,
            "se": float(np.std(inc, ddof=1) / np.sqrt(len(inc))) if len(inc) > 1 else None,
            **{f"vs {b}": paired(base[b], outcomes, scale=100)["paired"] for b in base},
        }
        vs = "  ".join(
            f"vs {b}: {rows[name][f'vs {b}']['mean']:+.1f} ± {rows[name][f'vs {b}']['se']:.1f}" for b in base
        )
        print(f"{name:>28} {rows[name]['goals']:>3}/{len(problems)} {rows[name]['mean'] or float('nan'):>8.1f}%  {vs}")

    for name, outcomes in base.items():
        row(f"{name} (target)", outcomes)
    for eps in noises:
        rng = np.random.default_rng(0)
        oracles = [OracleValue(c, directions(o.X.shape, rng), eps) for c, o in zip(models, optima, strict=True)]
        row(f"TTO-MPC (oracle value, ε={eps:g})", run(planner, "TTO-MPC", problems, mpc, oracles))
    summary = {
        "bench": "terminal_ceiling",
        "model": args.model,
        "protocol": args.protocol,
        "seed": args.seed,
        "problems": len(problems),
        "horizon": args.horizon,
        "curvature": curvature,
        "rows": rows,
        **machine.record(),
    }
    out = args.out or (None if args.quick else results_file(sc.name))
    write_result(summary, out, {"bench": "terminal_ceiling", "rows": rows})


if __name__ == "__main__":
    main()
