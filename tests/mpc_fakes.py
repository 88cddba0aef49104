"""A short free-flyer ("freeflyer-short": N = 40 steps, start and goal on either side of obstacle 0) so that MPC,
evaluation and DAgger tests run full episodes in seconds. The straight line crosses the obstacle, so REL solutions
violate the keep-out zone (ctg0 > 0), like the problems the paper's MPC study selects.

Imported by spawned workers (its import registers the scenario), so it must stay importable alone.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from ttompc.scenarios import register
from ttompc.scenarios.base import Problem
from ttompc.scenarios.freeflyer import DT, FreeFlyer

SHORT_STEPS = 40


@register
class FreeFlyerShort(FreeFlyer):
    name: ClassVar[str] = "freeflyer-short"
    version: ClassVar[str] = "0.1"
    n_steps: ClassVar[int] = SHORT_STEPS

    def sample(self, rng: np.random.Generator) -> Problem:
        x0, goal = np.zeros(6), np.zeros(6)
        x0[:2] = [0.55, 0.7 + rng.uniform(-0.05, 0.05)]
        goal[:2] = [1.45, 0.7 + rng.uniform(-0.05, 0.05)]
        x0[2], goal[2] = rng.uniform(-0.3, 0.3, size=2)
        return Problem(x0=x0, goal=goal, dt=DT, n_steps=SHORT_STEPS)

    def problem_from_features(self, x0: np.ndarray, goal: np.ndarray, dt: float, features: dict[str, Any]) -> Problem:
        return Problem(x0=x0, goal=goal, dt=float(dt), n_steps=SHORT_STEPS)


def tiny_planner(scenario_name: str = "freeflyer-short", seed: int = 0) -> Any:
    """A randomly initialised 1-layer Planner with plausible normalisation statistics (for plumbing tests)."""
    import torch

    from ttompc.policy import ModelConfig, Planner, TrajectoryGPT
    from ttompc.policy.stats import NormStats
    from ttompc.scenarios import get_scenario

    scenario = get_scenario(scenario_name)
    torch.manual_seed(seed)
    cfg = ModelConfig(n_embd=32, n_layer=1, n_head=2, max_steps=scenario.n_steps, dropout=0.0)
    n, m = scenario.state_dim, scenario.control_dim
    stats = NormStats(
        mean={"states": np.zeros(n), "actions": np.zeros(m), "goals": np.zeros(n), "rtg": [-0.3], "ctg": [5.0]},
        std={"states": np.ones(n), "actions": np.full(m, 3e-3), "goals": np.ones(n), "rtg": [0.2], "ctg": [5.0]},
    )
    return Planner(TrajectoryGPT(cfg), scenario, stats)


def perturb_batched_rollouts(monkeypatch: Any, rounding: float) -> None:
    """Make every batched transformer rollout (batch > 1) differ from the lone one as another CPU's rounding would:
    its generated states and actions times (1 + ``rounding``·N(0, 1)), seeded by the step (the same on every
    machine). On the CPU where a user's AVX2 machine first showed it, the batched and lone rollouts of one state
    differ by about 1e-7; this makes that difference, and what the closed loop does with it, testable anywhere."""
    import dataclasses

    import torch

    from ttompc.policy.rollout import RolloutContext

    rollout = RolloutContext.rollout

    def rounded(self: RolloutContext, horizon: int) -> Any:
        out = rollout(self, horizon)
        if self.batch == 1 or rounding == 0:
            return out
        g = torch.Generator().manual_seed(self.t)

        def noisy(x: torch.Tensor) -> torch.Tensor:
            return x * (1 + rounding * torch.randn(x.shape, generator=g, dtype=x.dtype))

        states = torch.cat([out.states[:, :1], noisy(out.states[:, 1:])], dim=1)  # the measured state is exact
        return dataclasses.replace(out, states=states, actions=noisy(out.actions))

    monkeypatch.setattr(RolloutContext, "rollout", rounded)


def record_plans(monkeypatch: Any) -> dict[int, list[Any]]:
    """Every window plan (``StepPlan``) the MPC controllers make from now on, by ``id`` of the controller's problem."""
    from ttompc.mpc.loop import MPCController

    plans: dict[int, list[Any]] = {}
    plan = MPCController.plan

    def recording(self: MPCController, t: int, x: np.ndarray) -> Any:
        p = plan(self, t, x)
        plans.setdefault(id(self.problem), []).append(p)
        return p

    monkeypatch.setattr(MPCController, "plan", recording)
    return plans
