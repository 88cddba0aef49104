"""Seeded held-out evaluation problems.

Evaluation problem i, attempt a draws from ``ttompc.seeding.eval_seed(root, i, a)``: a stream disjoint from dataset
generation, so evaluation problems are held out whatever seed a dataset used, and each problem is the same whatever
the number of workers. By default (``nonconvex_only``) only problems whose REL solution violates a keep-out zone
(ctg0 > 0, the paper's selection for the MPC study) are kept: on the others REL is already the optimum and every
warm start looks alike, which dilutes any difference between models.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ttompc.mpc.loop import EpisodeStart
from ttompc.scenarios.base import InfeasibleProblemError, Problem, Scenario
from ttompc.seeding import eval_seed
from ttompc.solvers.scp import SCPResult, solve_rel


@dataclass
class EvalProblem:
    """A held-out problem with its open-loop REL solution (the lower bound J_REL and the TTO conditioning)."""

    index: int
    seed: int
    problem: Problem
    rel: SCPResult
    rel_time: float
    ctg0: int  # keep-out violations of the REL solution (non-convexity factor before normalisation)

    @property
    def rel_cost(self) -> float:
        return float(self.rel.cost)

    @property
    def start(self) -> EpisodeStart:
        """Where its closed-loop episodes start: the problem, J_REL and its seed as the plant's seed (the same
        disturbances for every method)."""
        return EpisodeStart(self.problem, self.rel_cost, self.seed)


def first_solvable(
    scenario: Scenario, problems: Iterable[Problem], *, nonconvex_only: bool = False, backend: str = "auto"
) -> tuple[int, Problem, SCPResult, float, int] | None:
    """The first of ``problems`` that is valid, whose REL solves and (with ``nonconvex_only``) whose REL solution
    violates a keep-out zone: (attempt index, problem, REL result, REL solve time, ctg0); None if none qualifies."""
    for attempt, problem in enumerate(problems):
        try:
            scenario.validate(problem)
        except InfeasibleProblemError:
            continue
        t0 = time.perf_counter()
        rel = solve_rel(scenario, problem, backend=backend)
        rel_time = time.perf_counter() - t0
        if not rel.success:
            continue
        ctg0 = int(np.sum(scenario.violations(problem, rel.X[: problem.n_steps])))
        if nonconvex_only and ctg0 == 0:
            continue
        return attempt, problem, rel, rel_time, ctg0
    return None


def eval_problem(
    scenario: Scenario,
    root: int,
    index: int,
    *,
    nonconvex_only: bool = True,
    max_attempts: int = 100,
    backend: str = "auto",
) -> EvalProblem:
    """Problem ``index`` of the evaluation stream: the first attempt that is valid, whose REL solves and (with
    ``nonconvex_only``, the default) whose REL solution violates a keep-out zone (ctg0 > 0)."""
    draws = (scenario.sample(np.random.default_rng(eval_seed(root, index, a))) for a in range(max_attempts))
    found = first_solvable(scenario, draws, nonconvex_only=nonconvex_only, backend=backend)
    if found is None:
        kind = "non-convex " if nonconvex_only else ""
        raise RuntimeError(f"{scenario.name}: no {kind}evaluation problem {index} in {max_attempts} attempts")
    attempt, problem, rel, rel_time, ctg0 = found
    return EvalProblem(index, eval_seed(root, index, attempt), problem, rel, rel_time, ctg0)
