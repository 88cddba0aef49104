"""The one schema of a trajectory row, shared by open-loop datasets (REL and SCP solutions) and DAgger shards.

A row is one trajectory of one problem. Arrays use the transformer's *model* representation (RPOD: RTN) with
fixed shapes, N = ``scenario.n_steps`` controls and N+1 states x_0..x_N:

    states (N+1, n) f32     actions (N, m) f32       goal (n,) f32 (model representation)
    rtg (N,) f32            rtg_t = −Σ_{τ≥t} c(u_τ)  (scenario stage cost)
    ctg (N,) f32            ctg_t = Σ_{τ≥t} viol(x_τ) over states 0..N−1 (violated keep-out constraints)
    target_actions (N, m), target_next_states (N, n)   open loop: actions and states[1:]; DAgger: expert labels
    costates (N+1, n) f32   λ_t = ∂J*_t/∂s_t, the gradient of the cost-to-go from step t (−∂rtg_t/∂s_t) at the
                            row's states, in the model representation; NaN where unknown (REL rows, steps without
                            a converged expert solve, DAgger plan rows up to their start and where the expert's plan
                            misses the goal, shards written before the column: read as NaN)

plus the problem in the *optimisation* representation (``states_opt``, ``x0``, ``goal_opt``, ``dt`` and one
``feat_<name>`` column per ``scenario.problem_features`` entry, enough for ``problem_from_features``) and the
solver statistics (cost, iterations, status, solve_time, solver_time, violation).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from datasets import Array2D, Features, List, Value

from ttompc.scenarios.base import Problem, Scenario

SCHEMA_VERSION = 1
SOURCES = ("rel", "scp", "dagger")
SOURCE_CODES = {name: i for i, name in enumerate(SOURCES)}
FEATURE_PREFIX = "feat_"


def _array(shape: tuple[int, ...], dtype: str) -> Any:
    if len(shape) == 0:
        return Value(dtype)
    if len(shape) == 1:
        return List(Value(dtype), length=shape[0])
    if len(shape) == 2:
        return Array2D(shape=shape, dtype=dtype)
    raise ValueError(f"scenario features of rank {len(shape)} are not supported (shape {shape})")


def feature_shapes(scenario: Scenario) -> dict[str, tuple[int, ...]]:
    """Shapes of ``scenario.problem_features`` (taken from one problem drawn with a fixed seed)."""
    problem = scenario.sample(np.random.default_rng(0))
    return {k: np.shape(v) for k, v in scenario.problem_features(problem).items()}


def trajectory_features(scenario: Scenario) -> Features:
    """The ``datasets.Features`` of a trajectory row for ``scenario`` (explicit fixed-shape arrays)."""
    N, n, m = scenario.n_steps, scenario.state_dim, scenario.control_dim
    cols: dict[str, Any] = {
        "problem_id": Value("int64"),
        "seed": Value("int64"),
        "source": Value("string"),
        "iteration": Value("int32"),
        "states": Array2D(shape=(N + 1, n), dtype="float32"),
        "actions": Array2D(shape=(N, m), dtype="float32"),
        "goal": _array((n,), "float32"),
        "rtg": _array((N,), "float32"),
        "ctg": _array((N,), "float32"),
        "target_actions": Array2D(shape=(N, m), dtype="float32"),
        "target_next_states": Array2D(shape=(N, n), dtype="float32"),
        "costates": Array2D(shape=(N + 1, n), dtype="float32"),
        "states_opt": Array2D(shape=(N + 1, n), dtype="float32"),
        "x0": _array((n,), "float64"),
        "goal_opt": _array((n,), "float64"),
        "dt": Value("float64"),
        "cost": Value("float64"),
        "iterations": Value("int32"),
        "status": Value("string"),
        "solve_time": Value("float64"),
        "solver_time": Value("float64"),
        "violation": Value("float64"),
    }
    for name, shape in feature_shapes(scenario).items():
        cols[FEATURE_PREFIX + name] = _array(tuple(shape), "float64")
    return Features(cols)


def returns_to_go(scenario: Scenario, U: np.ndarray) -> np.ndarray:
    """rtg_t = −Σ_{τ≥t} c(u_τ), (N,)."""
    c = scenario.stage_cost(np.asarray(U, dtype=np.float64))
    return -np.cumsum(c[::-1])[::-1]


def constraints_to_go(scenario: Scenario, problem: Problem, X_opt: np.ndarray) -> np.ndarray:
    """ctg_t = Σ_{τ≥t} viol(x_τ) over the N states x_0..x_{N−1} (optimisation representation), (N,)."""
    N = scenario.n_steps
    v = np.asarray(scenario.violations(problem, np.asarray(X_opt)[:N]), dtype=np.float64)
    return np.cumsum(v[::-1])[::-1]


def model_costates(scenario: Scenario, problem: Problem, costates: np.ndarray) -> np.ndarray:
    """Costates λ_k = ∂J/∂x_k (T, n) of optimisation states x_0.. -> ∂J/∂s_k in the model representation s_k = M_k x_k
    (a linear map per step): λ_s = (∂x/∂s)ᵀ λ_x, the columns of ∂x_k/∂s_k from ``from_model_states``."""
    lam = np.asarray(costates, dtype=np.float64)
    T, n = lam.shape
    cols = [scenario.from_model_states(problem, np.tile(e, (T, 1))) for e in np.eye(n)]  # each (T, n): F_k e_j
    return np.stack([np.einsum("ki,ki->k", c, lam) for c in cols], axis=1)


def make_row(
    scenario: Scenario,
    problem: Problem,
    *,
    problem_id: int,
    seed: int,
    source: str,
    states: np.ndarray,
    actions: np.ndarray,
    iteration: int = -1,
    states_opt: np.ndarray | None = None,
    rtg: np.ndarray | None = None,
    ctg: np.ndarray | None = None,
    target_actions: np.ndarray | None = None,
    target_next_states: np.ndarray | None = None,
    costates: np.ndarray | None = None,
    cost: float = float("nan"),
    iterations: int = -1,
    status: str = "",
    solve_time: float = float("nan"),
    solver_time: float = float("nan"),
    violation: float = float("nan"),
) -> dict[str, Any]:
    """One row. ``states`` (N+1, n) are in the model representation; rtg/ctg default to the recomputation from
    the scenario (DAgger passes the learner's contexts), targets default to the open-loop ones, costates (model
    representation) to NaN."""
    if source not in SOURCES:
        raise ValueError(f"source must be one of {SOURCES}, got {source!r}")
    N, n, m = scenario.n_steps, scenario.state_dim, scenario.control_dim
    states = np.asarray(states, dtype=np.float64)
    actions = np.asarray(actions, dtype=np.float64)
    if states.shape != (N + 1, n) or actions.shape != (N, m):
        raise ValueError(f"expected states ({N + 1}, {n}) and actions ({N}, {m}), got {states.shape}, {actions.shape}")
    if states_opt is None:
        states_opt = scenario.from_model_states(problem, states)
    row: dict[str, Any] = {
        "problem_id": int(problem_id),
        "seed": int(seed),
        "source": source,
        "iteration": int(iteration),
        "states": states,
        "actions": actions,
        "goal": scenario.model_goal(problem),
        "rtg": returns_to_go(scenario, actions) if rtg is None else np.asarray(rtg).reshape(N),
        "ctg": constraints_to_go(scenario, problem, states_opt) if ctg is None else np.asarray(ctg).reshape(N),
        "target_actions": actions if target_actions is None else np.asarray(target_actions).reshape(N, m),
        "target_next_states": states[1:]
        if target_next_states is None
        else np.asarray(target_next_states).reshape(N, n),
        "costates": np.full((N + 1, n), np.nan) if costates is None else np.asarray(costates).reshape(N + 1, n),
        "states_opt": np.asarray(states_opt, dtype=np.float64),
        "x0": problem.x0,
        "goal_opt": problem.goal,
        "dt": float(problem.dt),
        "cost": float(cost),
        "iterations": int(iterations),
        "status": status,
        "solve_time": float(solve_time),
        "solver_time": float(solver_time),
        "violation": float(violation),
    }
    for name, value in scenario.problem_features(problem).items():
        row[FEATURE_PREFIX + name] = np.asarray(value, dtype=np.float64)
    return row


def problem_from_row(scenario: Scenario, row: dict[str, Any]) -> Problem:
    """Rebuild the problem of a stored row (e.g. to re-solve it or to roll out a model on it)."""
    feats = {k[len(FEATURE_PREFIX) :]: np.asarray(v) for k, v in row.items() if k.startswith(FEATURE_PREFIX)}
    return scenario.problem_from_features(np.asarray(row["x0"]), np.asarray(row["goal_opt"]), float(row["dt"]), feats)
