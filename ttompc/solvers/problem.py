"""What an SCP solve is asked, in two small frozen descriptions that a caller builds once and updates per solve (as
with an acados OCP or an OSQP problem): ``SCPProblem``, the problem (the scenario's problem over a window, with its
terminal condition, relaxation and cost mode), and ``SCPOptions``, how it is solved (backend, formulation,
trust-region schedule and tolerances). The starting guess is the solve's own argument (``solve_scp``).

What a user passes is checked where it enters (``check_problem``, ``SCPOptions``): another object than a scenario or
a problem, a problem the scenario cannot pose, an unknown backend or formulation is a one-line ``UserError``
(``InputError``; ``ConfigError`` for the options), in the words ``ttompc`` prints for it."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ttompc.errors import ConfigError, InputError
from ttompc.scenarios.base import InfeasibleProblemError, Problem, Scenario, SCPSettings, Window
from ttompc.solvers.backends.chain import check_backend
from ttompc.solvers.results import TerminalCost

Formulation = Literal["penalized", "reference"]


@dataclass(frozen=True, eq=False, init=False)
class SCPProblem:
    """``problem`` of ``scenario`` over ``window`` (default: the whole horizon [0, N)).

    * ``terminal``: the soft terminal term ‖diag(w)(x_{t+H} − target)‖₂; required for a window that stops before N.
      Without one, a window that reaches N keeps x_N = goal (hard in the reference formulation, penalised in the
      penalized one).
    * ``obstacles=False``: the REL relaxation (no keep-out constraints).
    * ``soft``: MPC soft mode: the stage cost weighted by the scenario's ``mpc.fuel`` and waypoint-type equalities as
      weighted 2-norm penalties; otherwise weight 1 and hard equalities.

    A receding-horizon controller builds one per problem and ``update``s its window, terminal term and mode per step.
    """

    scenario: Scenario
    problem: Problem
    window: Window
    terminal: TerminalCost | None
    obstacles: bool
    soft: bool

    def __init__(
        self,
        scenario: Scenario,
        problem: Problem,
        window: Window | None = None,
        terminal: TerminalCost | None = None,
        *,
        obstacles: bool = True,
        soft: bool = False,
    ) -> None:
        window = window or Window.full(problem)
        if terminal is None and not window.reaches_end:
            raise ValueError(f"window [{window.start}, {window.stop}) stops before the end and needs a terminal cost")
        object.__setattr__(self, "scenario", scenario)
        object.__setattr__(self, "problem", problem)
        object.__setattr__(self, "window", window)
        object.__setattr__(self, "terminal", terminal)
        object.__setattr__(self, "obstacles", obstacles)
        object.__setattr__(self, "soft", soft)

    def update(self, **changes: Any) -> SCPProblem:
        """A copy with ``changes`` to any of the fields, checked as a new description is."""
        return dataclasses.replace(self, **changes)

    @property
    def fuel_weight(self) -> float:
        """The stage cost's weight: ``mpc.fuel`` in soft mode, else 1."""
        return self.scenario.mpc.fuel if self.soft else 1.0

    @property
    def convex(self) -> bool:
        """The REL of a scenario whose REL is convex (``Scenario.rel_is_convex``): one subproblem solves it."""
        return not self.obstacles and self.scenario.rel_is_convex


@dataclass(frozen=True)
class SCPOptions:
    """How an SCP solve runs.

    * ``backend``: "auto" (the scenario's chain, see ``backends.backend_chain``: the Riccati interior-point kernel
      where the subproblem is a penalised QP, PIQP on the other subproblems without cones, QOCO/Clarabel on the
      others), "riccati" (the same), "piqp" (that chain without the kernel), "conic"
      (QOCO then Clarabel throughout), "clarabel", "qoco" or "cvxpy-naive" (the rebuild-every-iteration baseline),
      those three alone. The trust-region norm follows: the scenario's (``Scenario.trust_norm``), l2 for ``conic``
      and for the reference formulation with ``auto`` (the comparison paths, which solve with Clarabel).
    * ``formulation``: "penalized" (slack variables and virtual control, every subproblem feasible) or "reference"
      (hard linearised constraints, the authors'; an infeasible subproblem ends the solve), ``scp.py``.
    * ``settings``: the trust-region schedule, tolerances and iteration cap; None: the scenario's (``Scenario.scp``),
      or one iteration without trust region for a problem one subproblem solves (``SCPProblem.convex``).
    """

    backend: str = "auto"
    formulation: Formulation = "penalized"
    settings: SCPSettings | None = None

    def __post_init__(self) -> None:
        check_backend(self.backend)
        if self.formulation not in ("penalized", "reference"):
            raise ConfigError(f"unknown SCP formulation {self.formulation!r}", "choose 'penalized' or 'reference'")

    def update(self, **changes: Any) -> SCPOptions:
        """A copy with ``changes`` to any of the fields (e.g. real-time iteration's one-iteration ``settings``)."""
        return dataclasses.replace(self, **changes)


def check_problem(scenario: Scenario, problem: Problem) -> None:
    """Raise a one-line ``InputError`` for what ``scenario`` cannot solve as ``problem``: not a ``Scenario`` or not a
    ``Problem``, start or goal of another shape (another scenario's problem), another number of steps, non-finite
    values, or one without a solution (``Scenario.validate``'s ``InfeasibleProblemError``, an ``InputError``, as
    is)."""
    if not isinstance(scenario, Scenario):
        raise InputError(f"not a scenario: {scenario!r}", "pass ttompc.get_scenario(NAME)")
    if not isinstance(problem, Problem):
        raise InputError(f"not a {scenario.name} problem: {problem!r}", "pass scenario.sample(rng) or a Problem")
    n = scenario.state_dim
    shapes = (np.shape(problem.x0), np.shape(problem.goal))
    if shapes != ((n,), (n,)):
        raise InputError(f"a {scenario.name} problem has start and goal of shape ({n},), got {shapes}")
    try:
        scenario.validate(problem)
    except InfeasibleProblemError:
        raise
    except ValueError as err:
        raise InputError(str(err)) from None
