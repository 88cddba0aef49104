"""The plant the MPC loop controls: the scenario's exact dynamics, optionally perturbed.

A model-based controller is only tested by a plant that differs from its model. ``PlantNoise`` adds, per episode,

* an actuation gain error: the applied control is u ⊙ (1 + g) with g ~ N(0, ``gain_std``²) per control component,
  drawn once per episode (a miscalibrated thruster),
* actuation noise: + N(0, (``actuation_std``·control_scale)²) per step and component,
* process noise: + N(0, (``process_std``·state_scale)²) on the next state, per step and component,

in units of the scenario's characteristic magnitudes (``state_scale``, ``control_scale``). Each scenario sizes its
perturbed plant (``Scenario.perturbation``, ``PlantNoise.perturbed(scenario)``) so that the disturbance of the last
step, which no controller can undo, stays inside its goal tolerance ``terminal_tol``. The default: gain 5%,
actuation 2% of control_scale, process 0.2% of state_scale per step — free-flyer/quadrotor: 2 mm and 0.2 mm/s per
step; enough that plans made at t = 0 drift measurably over 100 steps, small enough that every method stays
feasible on most problems. RPOD, whose 1 m docking tolerance is 1% of its 100 m state scale and whose docking burn
is an episode's largest: gain 0.3%, actuation 1% of control_scale, process 0.05% of state_scale (5 cm of ROE).
A component left None is the scenario's own (``PlantNoise.resolve``): ``evaluate mpc``'s ``plant`` section is a
``PlantNoise`` of Nones, so ``plant.process_std=0.005`` overrides one component and keeps the scenario's others.

Draws come from one generator seeded by the episode's seed, so the same seed gives the same disturbances (and the
same executed trajectory for a deterministic controller) whatever the method, and another seed gives other ones.
The cost of an episode is the cost of the *commanded* controls (what the controller decided to spend). On the
perturbed plant a run is feasible when its keep-out depth and other path violations stay within ``path_tol`` (5
standard deviations of one step's process noise: 1 cm for free-flyer and quadrotor, 25 cm of ROE for RPOD), not
at 1e-5 m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ttompc.ranges import check_settings, setting
from ttompc.scenarios.base import Problem, Scenario

PLANT_STREAM = 0x706C616E  # "plan(t)": seeds of plant disturbances, disjoint from problem seeds


@dataclass(frozen=True)
class PlantNoise:
    """Magnitudes of the plant disturbances, relative to the scenario's state/control scales (see module doc); a
    None component is the scenario's own (``Scenario.perturbation``), filled in by ``resolve``."""

    gain_std: float | None = setting(0.0, ge=0, meaning="null: the scenario's own")
    actuation_std: float | None = setting(0.0, ge=0, meaning="null: the scenario's own")
    process_std: float | None = setting(0.0, ge=0, meaning="null: the scenario's own")

    def __post_init__(self) -> None:
        check_settings(self, recurse=False)  # frozen: it cannot derive from ``Checked``

    def stds(self, scenario: Scenario) -> tuple[float, float, float]:
        """(gain_std, actuation_std, process_std), every None component the scenario's own."""
        gain, actuation, process = scenario.perturbation
        return (
            gain if self.gain_std is None else self.gain_std,
            actuation if self.actuation_std is None else self.actuation_std,
            process if self.process_std is None else self.process_std,
        )

    def resolve(self, scenario: Scenario) -> PlantNoise:
        """These disturbances with every None component replaced by the scenario's own (``perturbed``)."""
        return PlantNoise(*self.stds(scenario))

    @property
    def nominal(self) -> bool:
        return self.gain_std == self.actuation_std == self.process_std == 0

    def path_tol(self, scenario: Scenario) -> float:
        """Path-constraint tolerance of a run on this plant: 5 standard deviations of one step's process noise on
        the scenario's largest state scale (free-flyer/quadrotor at the default: 1 cm of keep-out depth), at least
        1e-3 like the nominal plant. A disturbance can push a plan that grazes a keep-out boundary inside it before
        any controller reacts; runs are only infeasible when they go deeper than that."""
        scale = float(np.max(scenario.state_units()))
        return max(1e-3, 5.0 * self.stds(scenario)[2] * scale)

    @classmethod
    def perturbed(cls, scenario: Scenario) -> PlantNoise:
        """The disturbance of the evaluations' perturbed plant for ``scenario`` (``Scenario.perturbation``)."""
        gain_std, actuation_std, process_std = scenario.perturbation
        return cls(gain_std=gain_std, actuation_std=actuation_std, process_std=process_std)


class Plant:
    """Steps the scenario's exact dynamics with the disturbances of ``noise``; ``reset(seed)`` starts an episode."""

    def __init__(self, scenario: Scenario, noise: PlantNoise | None = None) -> None:
        self.scenario = scenario
        self.noise = (noise or PlantNoise()).resolve(scenario)
        self._gain_std, self._actuation_std, self._process_std = self.noise.stds(scenario)
        self._x_scale = scenario.state_units()
        self._u_scale = scenario.control_units()
        self._rng = np.random.default_rng(0)
        self._gain = np.ones(scenario.control_dim)

    def reset(self, seed: int) -> None:
        """Start an episode: disturbances drawn from ``SeedSequence(seed, spawn_key=(PLANT_STREAM,))``."""
        from ttompc.seeding import rng

        self._rng = rng(seed, PLANT_STREAM)
        self._gain = 1.0 + self._gain_std * self._rng.standard_normal(self.scenario.control_dim)

    def applied(self, u: np.ndarray) -> np.ndarray:
        """The control the actuators deliver for the commanded ``u`` (draws the step's actuation noise)."""
        if self.noise.nominal:
            return u
        return u * self._gain + self._actuation_std * self._u_scale * self._rng.standard_normal(u.shape)

    def step(self, problem: Problem, t: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The next state after commanding ``u`` at step ``t`` from ``x``."""
        x_next = self.scenario.step(problem, t, x, self.applied(u))
        if self._process_std > 0:
            x_next = x_next + self._process_std * self._x_scale * self._rng.standard_normal(x_next.shape)
        return x_next
