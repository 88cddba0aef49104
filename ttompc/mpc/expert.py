"""DAgger's expert (paper Alg. 1): the full-horizon SCP over [t, N) from the measured state x_t, started from REL
over [t, N) from x_t as a from-scratch solve does (REL at t = 0 is the episode's own). It labels DAgger's rollouts
(``ttompc.finetune.collect``) and is the reference of the target-error diagnostic
(``ttompc.evaluation.target_error``).

``Expert`` acts beside the learners' lockstep loop as a ``StepHook`` of ``run_mpc_batch``: at each labelled step of
an episode (``ExpertRollout.labelled``) it plans [t, N) from the measured state with the episode's
``ExpertController``, and in the episode's expert steps (``ExpertRollout.expert_steps``) its plan acts instead of the
learner's. Where the expert acts on consecutive steps its own converged plan's tail is reused when the state is on
it (plan reuse, ``ttompc.mpc.loop``). Warm-starting it from its previous plan shifted by one step instead (the
reference's expert) lands in worse local optima (measured in docs/scaling.md, "Label cost").
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ttompc.mpc.loop import MPCController, StepPlan
from ttompc.mpc.plant import PlantNoise
from ttompc.mpc.providers import ShiftProvider
from ttompc.mpc.settings import Mode, MPCSettings
from ttompc.mpc.tto import RolloutGroup
from ttompc.scenarios.base import Problem, Scenario, SCPSettings, Window
from ttompc.solvers.scp import SCPResult, TerminalCost, solve_rel


class ExpertController(MPCController):
    """The expert's ``MPCController``; ``costates``: its latest solve's ``SCPResult.costates`` (row 0 NaN) over the
    stage cost's weight in it (``SCPProblem.fuel_weight``) where its plan meets the goal (‖x_N − goal‖∞ <= the SCP's
    feas_tol: the soft end term is then an exact penalty, and λ the gradient of the cost the rtg counts, as in
    open-loop rows); None where it misses it (λ is then the gradient of the priced miss) or gave no multipliers."""

    costates: np.ndarray | None = None

    def solve(
        self,
        window: Window,
        X: np.ndarray,
        U: np.ndarray,
        terminal: TerminalCost | None,
        mode: Mode | None = None,
        settings: SCPSettings | None = None,
    ) -> SCPResult:
        res = super().solve(window, X, U, terminal, mode, settings)
        fuel = self.scenario.mpc.fuel if (mode or self.settings.mode) == "soft" else 1.0
        meets = float(np.max(np.abs(res.X[-1] - self.problem.goal))) <= self.scenario.scp.feas_tol
        self.costates = res.costates / fuel if res.costates is not None and meets else None
        return res


@dataclass
class ExpertRollout:
    """One episode beside the expert: its draws (seed, problem, its REL solution ``rel``, horizon H, the steps where
    the expert acts and those it labels, the plant) and its expert (a full-horizon ``ExpertController`` warm-started
    by ``shift``) with the plans it made at labelled steps. Made by ``start``."""

    index: int
    seed: int
    problem: Problem
    rel: Any  # the problem's REL solution (an SCPResult): the expert's start at t = 0
    H: int
    expert_steps: np.ndarray  # (N,) bool: the expert's plan acts
    labelled: np.ndarray  # (N,) bool: the expert plans from the measured state (every expert step is labelled)
    plant: PlantNoise
    shift: ShiftProvider
    expert: ExpertController
    plans: dict[int, StepPlan] = field(default_factory=dict)  # the expert's plan at each labelled step
    costates: dict[int, np.ndarray | None] = field(default_factory=dict)  # ... their Expert.plan_costates
    expert_time: float = 0.0

    @classmethod
    def start(
        cls,
        scenario: Scenario,
        draws: tuple[int, int, Problem, Any, int],
        expert_steps: np.ndarray,
        labelled: np.ndarray,
        plant: PlantNoise,
        settings: MPCSettings,
    ) -> ExpertRollout:
        """The episode of ``draws`` (index, seed, problem, its REL solution, H) with its expert under ``settings``
        (mode, backend, plan reuse), whose solves always converge (its provider's role is "expert", which
        ``MPCSettings.rti_for`` never gives real-time iteration, nor ``shift_for`` a shifted end start: its plans are
        labels)."""
        index, seed, problem, rel, H = draws
        shift = ShiftProvider()
        shift.reset(scenario, problem, rel.cost)
        expert = ExpertController(scenario, problem, shift, problem.n_steps, settings)
        return cls(index, seed, problem, rel, H, expert_steps, labelled | expert_steps, plant, shift, expert)


class Expert:
    """The expert beside the learners' lockstep loop (a ``StepHook`` of ``run_mpc_batch``, module doc): at each
    labelled step of an episode it plans [t, N) from the measured state, starting from REL over [t, N) from x_t as a
    from-scratch solve does (REL from the straight line, not warm-started by an earlier step's REL, which can stop at
    another point, and the label with it; REL at t = 0 is the episode's own); in the episode's expert steps its plan
    acts. Before each step it tells the learners' ``RolloutGroup`` (None: learners without one) the longest window
    they will ask, so one batched rollout serves them all."""

    def __init__(
        self, scenario: Scenario, rollouts: Sequence[ExpertRollout], group: RolloutGroup | None, backend: str
    ) -> None:
        self.scenario, self.rollouts, self.group, self.backend = scenario, rollouts, group, backend

    def before(self, t: int, controllers: Sequence[MPCController], xs: Sequence[np.ndarray]) -> list[StepPlan | None]:
        if self.group is not None:
            windows = [
                c.window(t).length for r, c in zip(self.rollouts, controllers, strict=True) if not r.expert_steps[t]
            ]
            self.group.expect(t, max(windows, default=0))
        acting: list[StepPlan | None] = []
        for r, x in zip(self.rollouts, xs, strict=True):
            e = self._label(r, t, x) if r.labelled[t] else None
            acting.append(e if r.expert_steps[t] else None)
        return acting

    def _label(self, r: ExpertRollout, t: int, x: np.ndarray) -> StepPlan:
        t0 = time.perf_counter()
        N = r.problem.n_steps
        start = (
            r.rel
            if t == 0
            else solve_rel(self.scenario, r.problem, window=Window(t, N - t, N), x_start=x, backend=self.backend)
        )
        r.shift.reset_plan(start.X, start.U)
        r.expert_time += time.perf_counter() - t0
        e = r.plans[t] = r.expert.plan(t, x)
        r.costates[t] = self.plan_costates(r, t, e)
        r.expert_time += e.warm_time + e.solve_time
        return e

    @staticmethod
    def plan_costates(r: ExpertRollout, t: int, e: StepPlan) -> np.ndarray | None:
        """The costates (N − t + 1, n) of the expert's plan ``e`` at step t over its steps t..N (optimisation
        representation, ``ExpertController.costates``): a solved plan's are its solve's; a reused plan's (plan reuse:
        the tail of the plan at t − 1, so recursively of the plan solved last) are those of the solve that produced
        it, shifted to steps t..N. Row 0 (step t, the solve's fixed start) is NaN in both, so reuse does not change
        which steps are labelled. None for a fallback plan and where the producing solve gave no costates."""
        lam = None if e.fallback else r.costates.get(t - 1) if e.reused else r.expert.costates
        if lam is None:
            return None
        lam = np.array(lam[1:] if e.reused else lam, dtype=np.float64)
        lam[0] = np.nan
        return lam

    def after(self, t: int, plans: Sequence[StepPlan], xs: Sequence[np.ndarray]) -> None:
        for r, plan, x_next in zip(self.rollouts, plans, xs, strict=True):
            if r.labelled[t]:
                r.expert.observe(r.plans[t], plan.u, x_next)
