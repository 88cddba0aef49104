"""Shared pieces of the evaluations: seeded held-out problems and a spawn process pool.

Evaluation problem i draws from ``SeedSequence(root, spawn_key=(EVAL_STREAM, i, attempt))``: a stream disjoint from
dataset generation (``spawn_key=(i,)``), so evaluation problems are held out whatever seed the dataset used, and
each problem is the same whatever the number of workers.
"""

from __future__ import annotations

import contextlib
import importlib
import multiprocessing as mp
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from ttompc.parallel import single_threaded_env
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import InfeasibleProblemError, Problem, Scenario
from ttompc.solvers.scp import SCPResult, solve_rel

EVAL_STREAM = 0x6576616C  # "eval"


def eval_seed(root: int, index: int, attempt: int = 0) -> int:
    state = np.random.SeedSequence(root, spawn_key=(EVAL_STREAM, index, attempt)).generate_state(1, dtype=np.uint64)
    return int(state[0] >> np.uint64(1))


@dataclass
class EvalProblem:
    """A held-out problem with its open-loop REL solution (the lower bound J_REL and the TTO conditioning)."""

    index: int
    seed: int
    problem: Problem
    rel: SCPResult
    rel_time: float
    ctg0: int  # keep-out violations of the REL solution (non-convexity factor before normalisation)


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
    nonconvex_only: bool = False,
    max_attempts: int = 100,
    backend: str = "auto",
) -> EvalProblem:
    """Problem ``index`` of the evaluation stream: the first attempt that is valid, whose REL solves and (with
    ``nonconvex_only``, like the paper's MPC study) whose REL solution violates a keep-out zone (ctg0 > 0)."""
    draws = (scenario.sample(np.random.default_rng(eval_seed(root, index, a))) for a in range(max_attempts))
    found = first_solvable(scenario, draws, nonconvex_only=nonconvex_only, backend=backend)
    if found is None:
        raise RuntimeError(f"{scenario.name}: no suitable evaluation problem {index} in {max_attempts} attempts")
    attempt, problem, rel, rel_time, ctg0 = found
    return EvalProblem(index, eval_seed(root, index, attempt), problem, rel, rel_time, ctg0)


def scenario_module(name: str) -> str:
    """The module that registers scenario ``name`` (imported by spawned workers, also for test scenarios)."""
    return type(get_scenario(name)).__module__


@contextlib.contextmanager
def single_torch_thread() -> Iterator[None]:
    """Batch-1 rollouts are chains of tiny kernels: extra OpenMP threads only add spin-waiting (we measured a 10-step
    rollout 100x slower with 2 threads than with 1 on a shared 2-core machine). Restores the previous count."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def worker_setup(module: str) -> None:
    """Import the scenario's module and use one torch thread (called once per worker process)."""
    importlib.import_module(module)
    import torch

    torch.set_num_threads(1)


def pool_map(
    fn: Callable[[Any], Any],
    tasks: Iterable[Any],
    workers: int,
    initializer: Callable[..., None],
    initargs: tuple[Any, ...],
) -> Iterator[Any]:
    """Results in task order: inline for ``workers <= 1``, else a spawn pool (fresh interpreters: no inherited RNG
    or torch state); ``initializer`` runs once per worker (e.g. loads the model once)."""
    tasks = list(tasks)
    if workers <= 1:
        with single_torch_thread():
            initializer(*initargs)
            yield from map(fn, tasks)
        return
    with single_threaded_env(), mp.get_context("spawn").Pool(min(workers, len(tasks)), initializer, initargs) as pool:
        yield from pool.imap(fn, tasks, chunksize=1)
