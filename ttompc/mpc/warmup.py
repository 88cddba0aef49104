"""No compilation inside an MPC step: ``warm_up`` runs, before an episode's first step, what a step would otherwise
compile (or load from numba's on-disk cache) at its first call.

Two parts of a step run numba code, compiled at the first call of a function with given argument types or loaded
from the disk cache: the Riccati kernel of the window solves (``ttompc.solvers.backends.riccati_kernel``; an MPC
window's terminal cone is a part of it that an open-loop solve never reaches) and the fused decode of TTO-MPC's
rollouts (``ttompc.policy.fused``: its rollout and KV-cache extension kernels and the scenario's dynamics step),
about 12 s compiling on a fresh machine and 0.4 s loading from the cache. Left to the first step, that time would
land in the first episode's step times: in the mean and largest step times of a process's first run, and in a
robot's first control step.

``warm_up`` solves a throwaway REL and two throwaway windows of the scenario (the first window and one that reaches
the end) as the run's settings pose them, and for every TTO provider whose rollouts decode with the fused kernel
one throwaway rollout, two context advances and a rollout of its model; once per process and key (scenario, backend
and mode; scenario, the model's number of layers and decoder), so only a process's first run pays it.
``run_mpc_batch`` calls it before its first step (``evaluate mpc``, the training callback, DAgger and the demo),
``ttompc.mpc.controller.Controller`` when it is built. A warm-up of ``NOTICE_SECONDS`` or more says so on stderr
(``ttompc.progress.status``: unless progress is off).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from ttompc.mpc.providers import Provider
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.tto import TTOProvider
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.scp import SCPOptions, SCPProblem, TerminalCost, solve_rel, solve_scp

NOTICE_SECONDS = 3.0  # a warm-up this long or longer (a compilation, not a cache load) is announced on stderr
_DONE: set[tuple[object, ...]] = set()  # what this process has warmed up (module doc)


def warm_up(
    scenario: Scenario, problem: Problem, providers: Sequence[Provider], horizon: int, settings: MPCSettings
) -> list[str]:
    """Run once per process what the steps of ``providers`` at ``horizon`` under ``settings`` would compile at their
    first call, on ``problem`` (module doc); returns what it warmed up now (empty when the process already had)."""
    t0 = time.perf_counter()
    done = []
    key: tuple[object, ...] = ("solver", scenario.name, settings.backend, settings.mode)
    if key not in _DONE:
        _solve(scenario, problem, horizon, settings)
        _DONE.add(key)
        done.append("the window solver")
    for p in providers:
        if isinstance(p, TTOProvider) and p.group.decoder != "torch":
            # numba specialises the fused kernels on the number of layers (the weights' tuple) and the scenario step
            key = ("decoder", scenario.name, p.planner.model.cfg.n_layer, p.group.decoder, p.group.use_cache)
            if key not in _DONE:
                _DONE.add(key)
                if _decode(scenario, problem, p, horizon):
                    done.append("the fused decoder")
    seconds = time.perf_counter() - t0
    if done and seconds >= NOTICE_SECONDS:
        from ttompc.progress import status

        status(
            f"ttompc: {' and '.join(done)} compiled (or loaded from numba's cache) in {seconds:.1f} s before the "
            "first MPC step"
        )
    return done


def _solve(scenario: Scenario, problem: Problem, horizon: int, settings: MPCSettings) -> None:
    """REL over the whole problem (REL-MPC's and TTO-MPC's J_REL) and two MPC windows from the straight line: the
    first one (soft terminal term on a target) and one that reaches the end (its end term in ``settings.mode``),
    as ``MPCController.solve`` poses them."""
    N, H, soft = problem.n_steps, min(horizon, problem.n_steps), settings.mode == "soft"
    options = SCPOptions(backend=settings.backend)
    solve_rel(scenario, problem, backend=settings.backend)
    scp = SCPProblem(scenario, problem)
    for window in (Window(0, H, N), Window(N - H, H, N)):
        X, U = scenario.initial_guess(problem, window, problem.x0)
        if window.reaches_end:
            terminal = TerminalCost(problem.goal, scenario.mpc.end) if soft else None
        else:
            terminal = TerminalCost(X[-1], np.asarray(scenario.mpc.target, dtype=np.float64))
        solve_scp(scp.update(window=window, terminal=terminal, soft=soft), X, U, options)


def _decode(scenario: Scenario, problem: Problem, provider: TTOProvider, horizon: int) -> bool:
    """A rollout, two context advances (the first claims the rollout's token, the second, with no rollout before
    it, runs the extension kernel: ``ttompc.policy.fused``) and a rollout of ``provider``'s model on ``problem`` when
    its rollouts decode with the fused kernel (the torch path compiles nothing); returns whether they do."""
    planner, group = provider.planner, provider.group
    ctx = planner.context([problem], rtg0=-1.0, use_cache=group.use_cache, decoder=group.decoder)
    if ctx.decoder != "fused":
        return False
    H = max(1, min(horizon, problem.n_steps - 2, planner.model.cfg.max_steps - 2))
    ctx.rollout(H)
    for k in (1, 2):
        s = scenario.to_model_states(problem, problem.x0[None], start=k)
        ctx.advance(np.zeros((1, scenario.control_dim)), s)
    ctx.rollout(H)
    return True
