"""Receding-horizon loop and warm-start providers (issue 6) on the short free-flyer of ``mpc_fakes``."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator

import mpc_fakes
import numpy as np
import pytest

import ttompc.mpc.loop as loop_module
from ttompc.mpc import DISTProvider, MPCController, RELProvider, ShiftProvider, TTOProvider, run_mpc
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Window
from ttompc.solvers.scp import SCPResult, SCPStatus, solve_problem, solve_rel


@pytest.fixture(autouse=True)
def _one_torch_thread() -> Iterator[None]:
    """Batch-1 rollouts: extra threads only spin on a shared machine."""
    from ttompc.parallel import single_torch_thread

    with single_torch_thread():
        yield


@pytest.fixture(scope="module")
def setup() -> tuple:
    sc = get_scenario(mpc_fakes.FreeFlyerShort.name)
    problem = sc.sample(np.random.default_rng(1))
    sc.validate(problem)
    rel, scp = solve_problem(sc, problem)
    assert rel.success and scp is not None and scp.success
    return sc, problem, rel, scp


def test_full_horizon_mpc_reproduces_open_loop_scp(setup: tuple) -> None:
    sc, problem, rel, scp = setup
    ep = run_mpc(sc, problem, RELProvider(), problem.n_steps, rel_cost=rel.cost, mode="hard")
    assert ep.complete and ep.feasible and ep.fallbacks == 0
    assert ep.cost == pytest.approx(scp.cost, rel=5e-3)
    assert ep.terminal_error < 1e-4
    assert ep.step_times.shape == (problem.n_steps,) and np.all(ep.step_times > 0)
    # the executed trajectory follows the exact dynamics
    np.testing.assert_allclose(sc.rollout(problem, ep.U), ep.X, atol=1e-9)


def test_windows_shrink_near_the_end(setup: tuple) -> None:
    sc, problem, _, _ = setup
    N = problem.n_steps
    ctrl = MPCController(sc, problem, RELProvider(), 10)
    assert [ctrl.window(t).length for t in (0, N - 10, N - 9, N - 1)] == [10, 10, 9, 1]
    assert ctrl.window(N - 3).reaches_end and not ctrl.window(0).reaches_end


def _check(ws, window: Window, x: np.ndarray, sc) -> None:
    assert ws.X.shape == (window.length + 1, sc.state_dim)
    assert ws.U.shape == (window.length, sc.control_dim)
    np.testing.assert_array_equal(ws.X[0], x)
    assert (ws.terminal is None) == window.reaches_end


def test_providers_respect_the_window(setup: tuple) -> None:
    sc, problem, rel, scp = setup
    N = problem.n_steps
    x = scp.X[5] + 1e-3  # a measured state off the plan
    planner = mpc_fakes.tiny_planner()
    shift = ShiftProvider()
    providers = [RELProvider(), DISTProvider(), TTOProvider(planner), shift]
    for prov in providers:
        prov.reset(sc, problem, rel.cost)
    shift.reset_plan(scp.X, scp.U)
    for prov in providers:
        w = Window(0, 10, N)
        ws = prov.warm_start(w, problem.x0)
        _check(ws, w, problem.x0, sc)
        if isinstance(prov, DISTProvider):
            np.testing.assert_array_equal(ws.terminal.target, problem.goal)
            np.testing.assert_array_equal(ws.terminal.weights, np.asarray(sc.mpc.dist, float))
        else:  # the target is the warm start's own state at t+H
            np.testing.assert_array_equal(ws.terminal.target, ws.X[-1])
            np.testing.assert_array_equal(ws.terminal.weights, np.full(6, sc.mpc.terminal))
    # REL-MPC: REL over the whole remaining horizon from x, truncated
    w = Window(5, 10, N)
    ws = providers[0].warm_start(w, x)
    _check(ws, w, x, sc)
    full = solve_rel(sc, problem, window=Window(5, N - 5, N), x_start=x)
    np.testing.assert_allclose(ws.X[1:], full.X[1:11], atol=1e-6)
    # near the end every provider's window is shorter and carries no terminal cost
    tto = providers[2]
    for t in range(N - 3):
        u = np.zeros(3)
        tto.observe(u, sc.step(problem, t, scp.X[t], u), scp.X, scp.U)
    w = Window(N - 3, 3, N)
    for prov in providers:
        _check(prov.warm_start(w, scp.X[N - 3]), w, scp.X[N - 3], sc)


def test_tto_context_is_advanced_not_recomputed(setup: tuple) -> None:
    """Per MPC step the model encodes O(H) new tokens (not the growing prefix), and the cached warm starts equal
    the reference-style full recomputation."""
    sc, problem, rel, _ = setup
    planner = mpc_fakes.tiny_planner()
    counts: list[int] = []
    encode = planner.model.encode

    def counting(tokens, cache=None):
        counts.append(tokens.shape[1])
        return encode(tokens, cache)

    planner.model.encode = counting  # type: ignore[method-assign]
    H = 5
    cached, full = TTOProvider(planner), TTOProvider(planner, use_cache=False)
    for prov in (cached, full):
        prov.reset(sc, problem, rel.cost)
    x = problem.x0
    for t in range(8):
        w = Window(t, H, problem.n_steps)
        counts.clear()
        a = cached.warm_start(w, x)
        cached_tokens = sum(counts)
        b = full.warm_start(w, x)
        np.testing.assert_allclose(a.X, b.X, atol=1e-5)
        np.testing.assert_allclose(a.U, b.U, atol=1e-6)
        assert cached_tokens == 4 + 5 * (H - 1)  # this window's tokens only, whatever t
        u = 0.5 * a.U[0]
        x_next = sc.step(problem, t, x, u)
        counts.clear()
        cached.observe(u, x_next, a.X, a.U)
        full.observe(u, x_next, b.X, b.U)
        assert sum(counts) == 5  # the executed step joins the cache: five tokens
        x = x_next
    assert cached.context.t == 8 and cached.context._cache.length == 5 * 8


def test_failed_step_falls_back_to_the_shifted_plan(setup: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    sc, problem, rel, _ = setup
    real = loop_module.solve_scp
    plans: list[np.ndarray] = []
    calls = {"n": 0}

    def flaky(scenario, prob, X, U, **kw):
        calls["n"] += 1
        res = real(scenario, prob, X, U, **kw)
        plans.append(res.U)
        if calls["n"] == 3:  # step t = 2 fails
            return SCPResult(SCPStatus.INFEASIBLE, res.X, res.U, res.cost, 1.0, res.iterations, 0.0, 0.0, res.window)
        return res

    monkeypatch.setattr(loop_module, "solve_scp", flaky)
    ep = run_mpc(sc, problem, DISTProvider(), 10, rel_cost=rel.cost, max_steps=4)
    assert ep.fallbacks == 1 and not ep.complete and len(ep.U) == 4
    np.testing.assert_array_equal(ep.U[2], plans[1][1])  # the previous plan's next control
    assert np.isnan(ep.terminal_error)


def test_importing_mpc_does_not_import_lightning() -> None:
    code = "import sys, ttompc.mpc; assert 'lightning' not in sys.modules and 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
