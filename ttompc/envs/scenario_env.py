"""``ScenarioEnv``: a ttompc scenario as a ``gymnasium.Env`` on our plant, for any controller to be tried on it.

An episode is one of the scenario's problems (``Scenario.sample`` drawn from the env's seeded generator at
``reset``, or the one given as ``options={"problem": ...}``), stepped for its N controls by ``ttompc.mpc.plant.Plant``:
the exact dynamics (``plant="nominal"``) or the evaluations' perturbed plant (``plant="perturbed"``: the scenario's
actuation error and process noise, ``PlantNoise.perturbed``, seeded from the env's generator).

* observation: the state (n,), in the scenario's optimisation representation (RPOD: scaled ROE), as ``Problem.x0``;
* action: the control (m,); the space is the box that holds every control the scenario's constraints allow
  (``control_bounds``: the quadrotor's ±10 N per component, the free-flyer's thruster bound over all headings,
  ``Scenario.control_box``), unbounded where they put none (RPOD's impulses: no Δv bound);
* reward: minus the stage cost c(u) (``Scenario.stage_cost``: the problem's objective, Σ c(u), is minus the return);
* ``terminated`` after the N-th control (never truncated);
* info: ``t`` (the step of the observation); at ``reset`` ``problem`` (the ``Problem``: what ``ttompc.Controller.reset``
  takes; also the env's ``problem``); at every step ``violation`` (the step's largest exact path-constraint violation:
  keep-out depth, bounds, cones) and, at the end, ``goal_reached`` (‖x_N − goal‖₂ <= the scenario's
  ``terminal_tol``) and ``terminal_error``.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from ttompc.errors import UserError
from ttompc.mpc.controller import check_problem, sample_problem
from ttompc.mpc.plant import Plant, PlantNoise
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import BlockKind, Problem, Scenario, Window

PLANTS = ("nominal", "perturbed")


def control_bounds(scenario: Scenario, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of the controls (m,): the bounds of the scenario's inequality rows on a single control component
    with no state term (e.g. a control box), from its constraints of ``problem``'s first step, within its
    ``control_box`` (e.g. the free-flyer's heading-dependent thruster bound); ±inf where neither bounds one."""
    m = scenario.control_dim
    box = scenario.control_box()
    low, high = np.full(m, -np.inf), np.full(m, np.inf)
    if box is not None:
        low, high = np.maximum(low, box[0]), np.minimum(high, box[1])
    window = Window(0, 1, problem.n_steps)
    X, U = scenario.initial_guess(problem, window, problem.x0)
    for b in scenario.constraints(problem, window, X, U, obstacles=False):
        if b.kind is not BlockKind.INEQ or b.Gu is None or np.any(b.Gx[0]):
            continue
        for row in range(b.rows_per_step):  # lower <= g·u <= h on one component j: a bound on u_j
            nonzero = np.flatnonzero(b.Gu[0, row])
            if len(nonzero) != 1:
                continue
            j = int(nonzero[0])
            g = float(b.Gu[0, row, j])
            up = b.h[0, row] / g
            down = -np.inf * np.sign(g) if b.lower is None else b.lower[0, row] / g
            lo, hi = (down, up) if g > 0 else (up, down)
            low[j], high[j] = max(low[j], lo), min(high[j], hi)
    return low, high


class ScenarioEnv(gymnasium.Env[np.ndarray, np.ndarray]):
    """A scenario's problems on the nominal or perturbed plant (module doc). ``scenario``: a registered name, a
    spec (``ttompc.scenarios.get_scenario``: a file or module of your own) or an instance."""

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012 (gymnasium.Env declares it so)

    def __init__(self, scenario: str | Scenario = "quadrotor", plant: str = "nominal") -> None:
        if plant not in PLANTS:
            raise UserError(f"unknown plant {plant!r}", f"use one of {list(PLANTS)}")
        self.scenario = get_scenario(scenario) if isinstance(scenario, str) else scenario
        self.plant_name = plant
        self.plant = Plant(self.scenario, PlantNoise.perturbed(self.scenario) if plant == "perturbed" else None)
        n, m = self.scenario.state_dim, self.scenario.control_dim
        self.observation_space = spaces.Box(-np.inf, np.inf, (n,), np.float64)
        low, high = control_bounds(self.scenario, sample_problem(self.scenario, np.random.default_rng(0)))
        self.action_space = spaces.Box(low, high, (m,), np.float64)
        self.problem: Problem | None = None
        self.t = 0
        self.x = np.zeros(n)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        given = (options or {}).get("problem")
        if given is not None:
            check_problem(self.scenario, given)
        self.problem = given if given is not None else sample_problem(self.scenario, self.np_random)
        self.plant.reset(int(self.np_random.integers(2**63 - 1)))
        self.t, self.x = 0, self.problem.x0.copy()
        return self.x.copy(), {"problem": self.problem, "t": 0}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        problem, sc = self.problem, self.scenario
        if problem is None or self.t >= problem.n_steps:
            raise UserError("step() outside an episode", "call reset() first")
        u = np.asarray(action)
        if u.shape != (sc.control_dim,) or u.dtype.kind not in "biuf" or not np.all(np.isfinite(u)):
            raise UserError(f"the action must be a finite real array of shape ({sc.control_dim},), got {u.tolist()}")
        u = u.astype(np.float64)
        x_next = self.plant.step(problem, self.t, self.x, u)
        violation = sc.path_violation(problem, np.stack([self.x, x_next]), u[None], Window(self.t, 1, problem.n_steps))
        self.t, self.x = self.t + 1, x_next
        info: dict[str, Any] = {"t": self.t, "violation": float(violation)}
        terminated = self.t == problem.n_steps
        if terminated:
            error = float(np.linalg.norm(x_next - problem.goal))
            info |= {"goal_reached": error <= sc.terminal_tol, "terminal_error": error}
        return x_next.copy(), -float(sc.stage_cost(u[None])[0]), terminated, False, info


def make_env(scenario: str | Scenario, plant: str = "nominal") -> ScenarioEnv:
    """Any scenario as a ``ScenarioEnv`` (a name, a spec of your own or an instance; ``plant``: nominal or
    perturbed); the shipped ones also as ``gymnasium.make("ttompc/<Name>-v1", plant=...)`` (``ttompc.envs``)."""
    return ScenarioEnv(scenario, plant)
