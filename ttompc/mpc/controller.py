"""``Controller``: the learned MPC (or a baseline) as one object with one call per step, for your own control loop.

    ctrl = Controller.from_pretrained("quadrotor-ft-tto-v6", horizon=10)   # or Controller("quadrotor", "REL-MPC")
    ctrl.reset(problem)             # a scenario Problem: start, goal and the scenario's extras
    u = ctrl.step(x)                # one MPC step from the measured state x, whatever produced it
    ctrl.last                       # the step's record: plan, target, SCP iterations and status, wall time

It is a thin facade over the code every closed-loop episode of ttompc runs (``ttompc.mpc.loop``): ``reset`` starts
the episode as ``run_mpc_batch`` does (``start_controller``: the method's provider, from ``ttompc.mpc.methods``,
reset for the problem, and an ``MPCController`` over it), and ``step(x)`` makes the two calls the loop makes for a
step, in its order: ``MPCController.observe`` of the previous step's outcome (the control this controller returned,
and ``x`` as the state it led to: TTO-MPC's KV-cache advance) and ``MPCController.plan`` from ``x``. So the
Controller driving ttompc's plant gives exactly the episode of ``ttompc evaluate mpc`` (one problem per lockstep
batch) on the same problem and plant, controls and cost (``tests/test_controller.py``). The settings come from a
protocol as in ``evaluate mpc`` (``recommended`` by default, with single-key ``overrides``).

Bad input is refused with one ``UserError`` line and leaves the controller as it was: an unknown method or
protocol, a model method without a model, a model of another scenario, a problem of another shape, ``step`` before
``reset`` or after the problem's N steps, a state of the wrong shape or with NaN or inf. A window whose SCP fails
is no error: the step applies the fallback control (the previous plan's next one, ``ttompc.mpc.loop``) and its
record says so (``StepRecord.status == "fallback"``). Building the controller compiles what its steps run
(``ttompc.mpc.warmup``), so no step compiles.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.errors import UserError
from ttompc.model_slots import slot_of
from ttompc.mpc.loop import EpisodeStart, MPCController, StepPlan, start_controller
from ttompc.mpc.methods import METHODS, ROBUST_BLEND, Method, MethodInputs, model_method
from ttompc.mpc.settings import MPCSettings, protocol_settings
from ttompc.mpc.warmup import warm_up
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import InfeasibleProblemError, Problem, Scenario
from ttompc.solvers.problem import check_problem

if TYPE_CHECKING:
    from ttompc.policy import Planner

WARMUP_SEED = 0  # the sample problem the warm-up plans on (ttompc.mpc.warmup)


@dataclass(frozen=True)
class StepRecord:
    """What one ``Controller.step`` did. ``status``: "converged" (the window's SCP met its stopping rule),
    "feasible" (its best feasible iterate, or a real-time iteration's one subproblem), "reused" (the previous plan's
    tail, optimal for this window: no solve) or "fallback" (the SCP failed: ``u`` is the previous plan's next
    control, or the warm start's first at step 0). ``X`` (H+1, n) and ``U`` (H, m) are the window's plan (its first
    control is ``u``), ``target`` its terminal target (None when the window reaches the end). ``seconds`` is the
    step's wall time, measured state to control: the facade's checks, ``observe_time`` (the previous outcome passed
    to the method, e.g. TTO-MPC's KV-cache advance), ``warm_time`` (warm start) and ``solve_time`` (SCP)."""

    t: int
    u: np.ndarray
    X: np.ndarray
    U: np.ndarray
    target: np.ndarray | None
    iterations: int
    status: str
    seconds: float
    observe_time: float
    warm_time: float
    solve_time: float

    @property
    def fallback(self) -> bool:
        return self.status == "fallback"

    @property
    def message(self) -> str:
        """One line on the step, e.g. for a log."""
        what = {
            "converged": "SCP converged",
            "feasible": "SCP returned a feasible iterate",
            "reused": "reused the previous plan (no solve)",
            "fallback": "SCP failed: applied the fallback control (the previous plan's next control)",
        }[self.status]
        return f"step {self.t}: {what} in {self.iterations} iterations, {1e3 * self.seconds:.1f} ms"


def sample_problem(scenario: Scenario, rng: np.random.Generator, attempts: int = 100) -> Problem:
    """The first of ``attempts`` draws of ``scenario.sample(rng)`` that ``scenario.validate`` accepts."""
    for _ in range(attempts):
        problem = scenario.sample(rng)
        try:
            scenario.validate(problem)
        except InfeasibleProblemError:
            continue
        return problem
    raise RuntimeError(f"{scenario.name}: no valid problem in {attempts} draws")


def _finite(value: np.ndarray, shape: tuple[int, ...], what: str) -> np.ndarray:
    """``value`` as a float64 array of ``shape`` with finite real entries, else a one-line ``UserError`` naming
    ``what``."""
    a = np.asarray(value)
    if a.shape != shape:
        raise UserError(f"{what} must have shape {shape}, got {a.shape}")
    if a.dtype.kind not in "biuf":
        raise UserError(f"{what} must hold real numbers, got {a.dtype} entries: {a.tolist()}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise UserError(f"{what} has NaN or inf entries: {a.tolist()}")
    return a


def _status(plan: StepPlan) -> str:
    if plan.fallback:
        return "fallback"
    if plan.reused:
        return "reused"
    return "converged" if plan.converged else "feasible"


class Controller:
    """One closed-loop method on one scenario, stepped by the caller (module doc).

    ``method``: a name of ``ttompc.mpc.methods.METHODS`` (REL-MPC, DIST-MPC, PLAN-ONCE, ORACLE-MPC need no model;
    TTO-MPC, R-TTO-MPC, FT-TTO-MPC and R-FT-TTO-MPC plan with ``planner``); ``horizon``: the planning horizon H;
    ``protocol`` and ``overrides``: the MPC settings (``protocol_settings``: a preset name or a YAML file, and
    single keys over it); ``robust_blend`` and ``rtg_scale``: as ``ttompc evaluate mpc`` takes them."""

    def __init__(
        self,
        scenario: str | Scenario,
        method: str = "REL-MPC",
        *,
        planner: Planner | None = None,
        horizon: int = 10,
        protocol: str = "recommended",
        overrides: Mapping[str, Any] | None = None,
        robust_blend: float = ROBUST_BLEND,
        rtg_scale: float | None = None,
    ) -> None:
        self.scenario = get_scenario(scenario) if isinstance(scenario, str) else scenario
        if method not in METHODS:
            raise UserError(f"unknown method {method!r}", f"use one of {list(METHODS)}")
        self.method: Method = METHODS[method]
        if self.method.model is not None and planner is None:
            raise UserError(f"{method} plans with a model", "use Controller.from_pretrained(MODEL, method=...)")
        if planner is not None and planner.scenario.name != self.scenario.name:
            raise UserError(f"the model was trained on {planner.scenario.name!r}, not {self.scenario.name!r}")
        if planner is not None and planner.model.cfg.max_steps < self.scenario.n_steps:
            raise UserError(
                f"the model plans {planner.model.cfg.max_steps} steps, {self.scenario.name} has {self.scenario.n_steps}"
            )
        N = self.scenario.n_steps
        if isinstance(horizon, bool) or not isinstance(horizon, int | np.integer) or not 1 <= horizon <= N:
            raise UserError(f"horizon must be an integer in [1, {N}] for {self.scenario.name}, got {horizon!r}")
        try:
            self.settings: MPCSettings = protocol_settings(protocol, overrides)
            self._inputs = MethodInputs(self.settings, [None], planner, robust_blend, rtg_scale)
            providers = self.method.providers(self._inputs)  # refuses a blend or scale it cannot run, here
        except ValueError as err:
            if isinstance(err, UserError):
                raise
            raise UserError(str(err)) from None
        self.planner, self.horizon, self.protocol = planner, horizon, protocol
        self.t = 0  # the step the next ``step`` plans
        self.last: StepRecord | None = None  # the last step's record
        self.problem: Problem | None = None
        self.rel_cost = float("nan")  # J_REL of the problem (TTO-MPC's conditioning; nan for a baseline)
        self._mpc: MPCController | None = None
        self._acted: StepPlan | None = None  # the plan whose control the last step returned
        self.warmed_up = warm_up(self.scenario, self._sample(), providers, horizon, self.settings)

    @classmethod
    def from_pretrained(
        cls,
        source: str | Path,
        *,
        horizon: int = 10,
        protocol: str = "recommended",
        method: str | None = None,
        scenario: str | Scenario | None = None,
        device: str = "cpu",
        **kwargs: Any,
    ) -> Controller:
        """A controller planning with a pretrained model: ``source`` as ``ttompc.load_pretrained`` takes it (zoo name,
        ``hf://ORG/NAME[@REV]``, bundle folder or ``.ckpt``). ``method`` None: the robust TTO-MPC of the model's
        kind (R-FT-TTO-MPC for a fine-tuned model, R-TTO-MPC otherwise: ``evaluate mpc``'s best method under the
        recommended protocol); a baseline name runs that baseline on the model's scenario. ``scenario``: refused
        unless it is the model's; other keyword arguments go to ``Controller``."""
        from ttompc.policy import Planner

        scenario = get_scenario(scenario) if isinstance(scenario, str) else scenario
        planner = Planner.from_pretrained(source, scenario, device=device)
        if method is None:
            method = model_method(slot_of(planner.extra), robust=True).name
        return cls(planner.scenario, method, planner=planner, horizon=horizon, protocol=protocol, **kwargs)

    def _sample(self) -> Problem:
        """A valid problem of the scenario (the warm-up's)."""
        return sample_problem(self.scenario, np.random.default_rng(WARMUP_SEED))

    def reset(self, problem: Problem, rel_cost: float | None = None) -> None:
        """Start an episode on ``problem`` at step 0. ``rel_cost``: J_REL, the cost of the problem's open-loop REL
        solution that TTO-MPC conditions on (rtg_0 = −J_REL); None: solved here (learned methods only)."""
        sc = self.scenario
        check_problem(sc, problem)
        if rel_cost is None and self.method.model is not None:
            from ttompc.solvers.scp import solve_rel

            rel_cost = float(solve_rel(sc, problem, backend=self.settings.backend).cost)
        if rel_cost is not None and not np.isfinite(rel_cost):
            raise UserError(
                f"J_REL of the problem is {rel_cost}, not a cost to condition the model on", "pass rel_cost="
            )
        [provider] = self.method.providers(self._inputs)  # fresh, as every run of evaluate mpc
        start = EpisodeStart(problem, float("nan") if rel_cost is None else rel_cost)
        self._mpc = start_controller(sc, start, provider, self.horizon, self.settings)
        self.problem, self.rel_cost = problem, start.rel_cost
        self.t, self.last, self._acted = 0, None, None

    def step(self, x: np.ndarray, applied: np.ndarray | None = None) -> np.ndarray:
        """One MPC step from the measured state ``x`` (n,): the control to apply now, (m,). ``x`` is taken as the
        state the previous step's control led to, and that control as the one it returned unless ``applied`` says
        what was applied instead (a saturated or overridden actuator). ``last`` then holds the step's record."""
        t0 = time.perf_counter()
        mpc, problem, sc = self._mpc, self.problem, self.scenario
        if mpc is None or problem is None:
            raise UserError("step() before reset(problem)", "call reset(problem) to start an episode")
        if self.t >= problem.n_steps:
            raise UserError(f"the episode's N = {problem.n_steps} steps are done", "reset(problem) starts another")
        x = _finite(x, (sc.state_dim,), "the state")
        if applied is not None:
            if self._acted is None:
                raise UserError("applied= names the previous step's control, and this is the episode's first step")
            applied = _finite(applied, (sc.control_dim,), "the applied control")
        acted = self._acted
        observed = 0.0 if acted is None else mpc.observe(acted, acted.u if applied is None else applied, x)[0]
        plan = mpc.plan(self.t, x)
        self._acted = plan
        self.last = StepRecord(
            self.t,
            plan.u.copy(),
            plan.X,
            plan.U,
            plan.target,
            plan.iterations,
            _status(plan),
            time.perf_counter() - t0,
            observed,
            plan.warm_time,
            plan.solve_time,
        )
        self.t += 1
        return plan.u.copy()

    @property
    def name(self) -> str:
        """The method as the reports name it (a model method with the rtg mode its model runs, ``Method.label``)."""
        return self.method.label(self.settings, self.planner)
