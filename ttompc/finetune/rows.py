"""The schema rows of a finished DAgger rollout (``ttompc.finetune.collect`` documents the labels): a trajectory row
with its targets (``trajectory_row``) and a ``plan`` label's row, the visited prefix continued by the expert's plan
with its costates (``plan_row``)."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from ttompc.data.schema import make_row, model_costates
from ttompc.mpc.loop import StepPlan
from ttompc.scenarios.base import Problem, Scenario


def trajectory_row(
    scenario: Scenario,
    problem: Problem,
    X: np.ndarray,
    U: np.ndarray,
    S: np.ndarray,
    rtg: np.ndarray,
    ctg: np.ndarray,
    target_actions: np.ndarray,
    target_next: np.ndarray,
    status: str,
    common: dict[str, Any],
    costates: np.ndarray | None = None,
) -> dict[str, Any]:
    """A DAgger row of the trajectory (X, U) with model states S: its cost and keep-out violations, the targets and
    the costates (N+1, n) in the model representation (None: unknown, NaN)."""
    return make_row(
        scenario,
        problem,
        states=S,
        states_opt=X,
        actions=U,
        rtg=rtg,
        ctg=ctg,
        target_actions=target_actions,
        target_next_states=target_next,
        costates=costates,
        cost=scenario.cost(U),
        status=status,
        violation=float(np.sum(scenario.violations(problem, X))),
        **common,
    )


def plan_row(
    scenario: Scenario,
    problem: Problem,
    X: np.ndarray,
    U: np.ndarray,
    rtg: np.ndarray,
    ctg: np.ndarray,
    t: int,
    e: StepPlan,
    costates: np.ndarray | None,
    status: str,
    common: dict[str, Any],
    rtg_label: Literal["learner", "expert"],
) -> dict[str, Any]:
    """The row of a ``plan`` label at step t: the visited prefix (states x_0..x_t, executed u_0..u_(t-1), the learner's
    rtg/ctg) followed by the expert's plan from x_t over [t, N); targets (the plan's controls and next states) from t
    on, NaN (no loss) before. From t the rtg is, with ``rtg="learner"``, the learner's value run on as the context
    runs it (rtg_(s+1) = rtg_s + c(u*_s)); with ``rtg="expert"`` the plan's own cost-to-go −Σ_(k>=s) c(u*_k), as in
    open-loop rows. The ctg is held (the expert plan is feasible). ``costates`` (N − t + 1, n), the plan's λ over
    steps t..N in the optimisation representation (``expert.Expert.plan_costates``), fill the row's costates from
    step t, converted as open-loop rows' are (``model_costates``); steps before t, and all of them when
    ``costates`` is None, are NaN (the DataModule masks them)."""
    N = problem.n_steps
    Xr = np.concatenate([X[:t], e.X])  # (N+1, n)
    Ur = np.concatenate([U[:t], e.U])  # (N, m)
    S = scenario.to_model_states(problem, Xr)
    stage = scenario.stage_cost(e.U)  # (N - t,)
    if rtg_label == "expert":
        togo = -np.cumsum(stage[::-1])[::-1]
    else:
        togo = rtg[t] + np.concatenate([[0.0], np.cumsum(stage[:-1])])
    rtg_r = np.concatenate([rtg[:t], togo])
    ctg_r = np.concatenate([ctg[:t], np.full(N - t, ctg[t])])
    target_actions = np.full_like(Ur, np.nan)
    target_actions[t:] = e.U
    target_next = np.full((N, S.shape[1]), np.nan)
    target_next[t:] = S[t + 1 :]
    lam = np.full((N + 1, S.shape[1]), np.nan)
    if costates is not None:
        lam[t:] = costates
    status = f"{status};plan_from={t}"
    return trajectory_row(
        scenario,
        problem,
        Xr,
        Ur,
        S,
        rtg_r,
        ctg_r,
        target_actions,
        target_next,
        status,
        common,
        model_costates(scenario, problem, lam),
    )
