"""``ttompc evaluate target``: how far a method's terminal target is from where the optimal plan from the measured
state will be, along its closed-loop episodes (issue 57's cheap proxy for the closed loop; docs/evaluation.md,
"Target error").

The episodes are those of ``evaluate mpc`` (``ClosedLoopConfig``: protocol and overrides, plants, horizons,
held-out problems, seed) for one method (``method``; default the robust variant of the model given, R-FT-TTO-MPC
with ``ft_model``, else R-TTO-MPC; any method of ``ttompc.mpc.methods`` runs, REL-MPC and ORACLE-MPC as references).
Beside them, at every ``every``-th step t, DAgger's expert (``ttompc.mpc.expert.Expert``: REL, then SCP over
[t, N) from the *measured* state x_t) plans the rest of the episode; the method acts at every step, so its episodes
are the ones ``evaluate mpc`` runs (up to the rounding of a lockstep batch). A step whose expert plan converged
(``expert_fallback`` false) gives (``step_errors``):

* ``target_raw``: ‖(x̂_{t+L} − x*_{t+L}) / state_scale‖₂ for a window [t, t + L) that stops before N: the provider's
  plan at the window's end (a model's rollout, REL's plan, the oracle's optimum) against the expert's plan;
* ``target_blended``: the same for the window's terminal target, the setting in force (the robust blend of the R-
  methods; under ``terminal=value`` the target carries no weight and is reported all the same);
* ``control``: ‖(u_t − u*_t) / control_scale‖₂, the window's first control (the applied one) against the expert's;
* ``control_raw``: the same for the provider's own first control (the model's action; none on a step whose plan
  was reused, ``ttompc.mpc.loop``).

Normalisation: per component by the scenario's characteristic magnitudes (``Scenario.state_units``,
``control_units``; the units of ``target_change``), then the Euclidean norm, so that one number weighs every
component alike and compares across steps, plants and models of a scenario. The report
(``ttompc.evaluation.target_error_report``) aggregates by plant, horizon and steps to go, and correlates each
episode's mean with its closed-loop cost. Expert solves dominate the cost (one full-horizon SCP per labelled step):
``every`` subsamples them, problems run in the spawn pool in tasks of ``batch`` (their episodes in lockstep).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.errors import UserError
from ttompc.evaluation.closed_loop import ClosedLoopConfig, model_sources, tasks
from ttompc.evaluation.episodes import episode_record
from ttompc.evaluation.problems import EvalProblem
from ttompc.evaluation.report_files import claim_report
from ttompc.evaluation.target_error_report import ERRORS, write_target_report
from ttompc.evaluation.warmstart import default_workers
from ttompc.model_slots import FINE_TUNED, PRETRAINED, slot_flag
from ttompc.mpc.episode import Episode
from ttompc.mpc.expert import Expert, ExpertRollout
from ttompc.mpc.loop import MPCRun, StepPlan, run_mpc_batch
from ttompc.mpc.methods import METHODS, Method, MethodInputs, model_method
from ttompc.mpc.plant import PlantNoise
from ttompc.mpc.providers import Provider, WarmStart
from ttompc.mpc.tto import TTOProvider
from ttompc.parallel import WorkerState, pool_map
from ttompc.progress import Bar
from ttompc.ranges import setting
from ttompc.scenarios import get_scenario, scenario_spec
from ttompc.scenarios.base import Problem, Scenario, Window

if TYPE_CHECKING:
    from ttompc.policy import Planner


@dataclass
class TargetErrorConfig(ClosedLoopConfig):
    """``ttompc evaluate target`` settings: a closed-loop measurement (``ClosedLoopConfig``; default horizon 10 on
    both plants) of one ``method`` (None: R-FT-TTO-MPC with ``ft_model``, else R-TTO-MPC; without the R- under
    ``robust_blend=0``), the expert planning at
    every ``every``-th step; ``plot``: also write ``target_error.png``; ``out`` defaults to
    ``outputs/evaluate/target-<scenario>``."""

    method: str | None = None
    every: int = setting(1, ge=1)  # the expert plans at every k-th step
    plot: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.method is not None and self.method not in METHODS:
            raise ValueError(f"method must be one of {list(METHODS)}, got {self.method!r}")

    def method_entry(self) -> Method:
        """The method measured; raises ``UserError`` when it plans with a model the config does not name."""
        name = self.method or model_method(FINE_TUNED if self.ft_model else PRETRAINED, self.robust_blend > 0).name
        m = METHODS[name]
        if m.model is not None and m.model not in model_sources(self):
            flag = slot_flag(m.model)
            raise UserError(f"method={name} plans with a model and none is given", f"pass {flag} NAME")
        if m.robust and not self.robust_blend > 0:
            raise UserError(f"method={name} needs robust_blend > 0, got {self.robust_blend}", "drop the R- prefix")
        return m


@dataclass(frozen=True)
class RecordedWindow:
    """What a provider gave one window: its length L, the state of its plan at the window's end (``end``), the
    terminal target (None: the window reaches N) and its first control."""

    length: int
    end: np.ndarray
    target: np.ndarray | None
    u0: np.ndarray


class WindowRecorder:
    """A provider that is ``inner`` and records each window it gives (``windows``, by step; reset per episode)."""

    def __init__(self, inner: Provider) -> None:
        self.inner, self.name, self.role = inner, inner.name, inner.role
        self.windows: dict[int, RecordedWindow] = {}

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        self.windows = {}
        self.inner.reset(scenario, problem, rel_cost)

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        ws = self.inner.warm_start(window, x)
        target = None if ws.terminal is None else np.array(ws.terminal.target, dtype=np.float64)
        self.windows[window.start] = RecordedWindow(window.length, ws.X[-1].copy(), target, ws.U[0].copy())
        return ws

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> float | None:
        return self.inner.observe(u, x_next, plan_X, plan_U)


def step_errors(
    scenario: Scenario,
    n_steps: int,
    U: np.ndarray,
    windows: Mapping[int, RecordedWindow],
    plans: Mapping[int, StepPlan],
) -> list[dict[str, Any]]:
    """One row per step t the expert planned (``plans``: its plan over [t, N) from x_t): t, steps to go N − t,
    ``expert_fallback`` and the errors of ``ERRORS`` (module doc; nan where a step has none) of the executed
    controls ``U`` (T, m) and the provider's ``windows``."""
    xs, us = scenario.state_units(), scenario.control_units()
    rows = []
    for t, e in sorted(plans.items()):
        row: dict[str, Any] = {"t": t, "to_go": n_steps - t, "expert_fallback": bool(e.fallback)}
        row.update(dict.fromkeys(ERRORS, float("nan")))
        if not e.fallback and t < len(U):
            row["control"] = float(np.linalg.norm((U[t] - e.U[0]) / us))
            w = windows.get(t)
            if w is not None:
                row["control_raw"] = float(np.linalg.norm((w.u0 - e.U[0]) / us))
                if w.target is not None:
                    row["target_raw"] = float(np.linalg.norm((w.end - e.X[w.length]) / xs))
                    row["target_blended"] = float(np.linalg.norm((w.target - e.X[w.length]) / xs))
        rows.append(row)
    return rows


def expert_episodes(
    scenario: Scenario,
    eps: Sequence[EvalProblem],
    providers: Sequence[Provider],
    run: MPCRun,
    every: int = 1,
) -> tuple[list[Episode], list[list[dict[str, Any]]]]:
    """The episodes of ``eps`` with ``providers`` (one each; TTO providers of one ``RolloutGroup``) as ``run`` says,
    in lockstep, DAgger's expert planning beside them at every ``every``-th step under ``run.settings``: the
    episodes and each one's ``step_errors`` rows."""
    recorders = [WindowRecorder(p) for p in providers]
    group = providers[0].group if providers and isinstance(providers[0], TTOProvider) else None
    rollouts = []
    for ep in eps:
        N = ep.problem.n_steps
        labelled = np.arange(N) % every == 0
        draws = (ep.index, ep.seed, ep.problem, ep.rel, run.horizon)
        plant = run.plant or PlantNoise()
        rollouts.append(ExpertRollout.start(scenario, draws, np.zeros(N, dtype=bool), labelled, plant, run.settings))
    hook = Expert(scenario, rollouts, group, run.settings.backend)
    episodes = run_mpc_batch(scenario, [ep.start for ep in eps], recorders, run, hook=hook)
    rows = [
        step_errors(scenario, r.problem.n_steps, e.U, rec.windows, r.plans)
        for r, e, rec in zip(rollouts, episodes, recorders, strict=True)
    ]
    return episodes, rows


def target_errors(
    scenario: Scenario,
    eps: Sequence[EvalProblem],
    planner: Planner | None,
    cfg: TargetErrorConfig,
    on_episode: Callable[[], None] | None = None,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Every (plant, H) of ``cfg`` for the problems ``eps`` with ``cfg``'s method (``planner`` in its model slot):
    the episodes' records (``episode_record`` with the problem and the episode's mean of each error) and the step
    rows (``step_errors`` with the problem, plant and horizon)."""
    method = cfg.method_entry()
    records: list[dict[str, Any]] = []
    steps: list[dict[str, Any]] = []
    for plant, run in cfg.runs(scenario):
        inputs = MethodInputs(cfg.settings, [None] * len(eps), planner, cfg.robust_blend, cfg.rtg_scale)
        episodes, rows = expert_episodes(scenario, eps, method.providers(inputs), run, cfg.every)
        for ep, e, ep_rows in zip(eps, episodes, rows, strict=True):
            key = {"problem": ep.index, "plant": plant, "horizon": run.horizon}
            means = {k: _nanmean([r[k] for r in ep_rows]) for k in ERRORS}
            fallbacks = sum(r["expert_fallback"] for r in ep_rows)
            records.append({**key, **episode_record(e), **means, "expert_fallbacks": fallbacks})
            steps += [{**key, **r} for r in ep_rows]
            if on_episode is not None:
                on_episode()
    return records, steps


def _nanmean(values: Sequence[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


@dataclass
class _Worker:
    """What ``_init`` loads once per pool worker for ``_run``."""

    cfg: TargetErrorConfig
    scenario: Scenario
    planner: Planner | None
    tick: Callable[[], None]


_WORKER: WorkerState[_Worker] = WorkerState()


def _init(cfg: dict[str, Any], tick: Callable[[], None]) -> None:
    from ttompc.config import from_container
    from ttompc.policy import Planner

    c = from_container(TargetErrorConfig, cfg)
    assert c.scenario is not None  # the caller resolved it before starting the workers
    scenario = get_scenario(c.scenario)
    slot = c.method_entry().model
    source = model_sources(c).get(slot) if slot else None
    planner = Planner.from_pretrained(source, scenario, device=c.device) if source else None
    _WORKER.set(_Worker(c, scenario, planner, tick))


def _run(indices: tuple[int, ...]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    w = _WORKER.get()
    return target_errors(w.scenario, w.cfg.problem_set(w.scenario, indices), w.planner, w.cfg, w.tick)


def run_target_error(cfg: TargetErrorConfig) -> dict[str, Any]:
    """Run the diagnostic; writes ``target_error.json``, ``target_error.md``, ``target_error_steps.csv`` (and with
    ``plot`` ``target_error.png``) into ``cfg.out`` (default ``outputs/evaluate/target-<scenario>``, a folder claimed
    before any work: ``report_files.claim_report``; ``target_error_report.write_target_report``)."""
    from ttompc.config import to_container

    if cfg.scenario is None:
        raise ValueError("TargetErrorConfig.scenario is not set (the command takes it from the model)")
    sc = get_scenario(cfg.scenario)
    too_long = sorted({h for h in cfg.horizons if h > sc.n_steps})
    if too_long:
        raise UserError(
            f"horizons {too_long} exceed the horizon of {sc.name}, N = {sc.n_steps} steps",
            f"pass horizons of at most {sc.n_steps}",
        )
    cfg.method_entry()  # a method without its model is one error line before the pool starts
    cfg.horizons = sorted(set(cfg.horizons))
    out = claim_report(cfg.out or f"outputs/evaluate/target-{sc.name}", "target")
    workers = default_workers(cfg.workers)
    t0 = time.perf_counter()
    records: list[dict[str, Any]] = []
    steps: list[dict[str, Any]] = []
    total = cfg.problems * len(cfg.plants) * len(cfg.horizons)
    with Bar(total, f"target error {sc.name}", "episode") as bar:
        init = (to_container(cfg), bar.ticker())
        for rs, ss in pool_map(
            _run, tasks(cfg.problems, cfg.batch), workers, _init, init, scenarios=[scenario_spec(sc)]
        ):
            records += rs
            steps += ss
    run = {
        "scenario": sc.name,
        "method": cfg.method_entry().name,
        "config": to_container(cfg),
        "settings": asdict(cfg.settings),
        "seconds": time.perf_counter() - t0,
    }
    return write_target_report(run, records, steps, out, cfg.plot)
