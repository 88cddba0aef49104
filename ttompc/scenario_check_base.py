"""What the checks of ``ttompc.scenario_check`` share: the sampled problems, scales and references of one run
(``CheckContext``), the failure a check raises (``CheckFailure``, via ``fail``) and the probes they use."""

from __future__ import annotations

from typing import NoReturn

import numpy as np

from ttompc.scenarios.base import InfeasibleProblemError, Problem, Scenario, Window
from ttompc.seeding import problem_seed

MODEL_TOL = 1e-8  # relative, in units of the scenario's scales: affine model and torch model against ``step``


class CheckFailure(Exception):
    """One failed check; the message is the one line shown to the user."""


class CheckContext:
    """Sampled problems, scales and references shared by the checks (each built on first use)."""

    def __init__(self, sc: Scenario, problems: int, seed: int, backend: str) -> None:
        self.sc, self.n_problems, self.seed, self.backend = sc, problems, seed, backend
        self.sx, self.su = sc.state_units(), sc.control_units()
        self.rng = np.random.default_rng(seed)
        self._problems: list[tuple[int, Problem]] | None = None

    def problems(self) -> list[tuple[int, Problem]]:
        """(seed, problem) of the first ``n_problems`` sampled problems that pass ``validate``."""
        if self._problems is None:
            out: list[tuple[int, Problem]] = []
            i = 0
            while len(out) < self.n_problems and i < 20 * self.n_problems:
                s = problem_seed(self.seed, i)
                p = self.sc.sample(np.random.default_rng(s))
                i += 1
                try:
                    self.sc.validate(p)
                except InfeasibleProblemError:
                    continue
                out.append((s, p))
            if not out:
                raise CheckFailure(f"validate() rejected all of {i} sampled problems")
            self._problems = out
        return self._problems

    def controls(self, H: int) -> np.ndarray:
        """Random controls of the declared control magnitudes (H, m)."""
        return self.rng.normal(size=(H, self.sc.control_dim)) * self.su

    def reference(self, problem: Problem) -> tuple[np.ndarray, np.ndarray]:
        """A dynamically consistent full-horizon reference: random controls rolled out from x0."""
        U = self.controls(problem.n_steps)
        return self.sc.rollout(problem, U), U

    def windows(self, problem: Problem) -> list[Window]:
        """The full horizon and a late receding-horizon window (MPC's windows start anywhere)."""
        N = problem.n_steps
        late = max(N // 2, N - 10)
        return [Window.full(problem), Window(late, N - late, N)]


def fail(message: str) -> NoReturn:
    raise CheckFailure(message)


def worst(err: np.ndarray) -> tuple[tuple[int, ...], float]:
    """Index and value of the largest entry: a failure names where it is worst."""
    idx = np.unravel_index(int(np.argmax(err)), err.shape)
    return tuple(int(i) for i in idx), float(err[idx])


def probe_states(ctx: CheckContext, p: Problem) -> np.ndarray:
    """States (N+1, n) that cross keep-out zones: the straight line to the goal, with the declared zones' centres
    (and points just inside their boundary) written over some of its states."""
    X = ctx.sc.initial_guess(p)[0].copy()
    centres, radii = ctx.sc.keepout_zones(p)
    k = 1
    for c, r in zip(np.asarray(centres, float), np.asarray(radii, float), strict=True):
        for point in (c, c + 0.9 * r * np.eye(len(c))[0]):
            if k < len(X) - 1:
                X[k, : len(c)] = point
                k += 2
    return X
