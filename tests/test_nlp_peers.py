"""The NLP peers of ``bench/solver_speed.py`` (built-once IPOPT and fatrop through CasADi, the ``peer`` extra) pose
the scenarios' problems: on problems whose keep-out constraints are active they reach our REL + SCP optimum, with
feasible trajectories, and fatrop sees the stage structure it is posed for."""

from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import pytest

from ttompc.scenarios import get_scenario
from ttompc.solvers import solve_problem

pytest.importorskip("casadi")

BENCH = Path(__file__).resolve().parents[1] / "bench"
# (scenario, seed): problems whose REL path crosses an obstacle, so the full NLP differs from REL
CASES = [("quadrotor", 3), ("freeflyer", 0)]


@pytest.fixture
def peers(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))  # as `python bench/solver_speed.py` imports them
    return {name: importlib.import_module(f"{name}_peer") for name in ("ipopt", "fatrop")}


@pytest.mark.parametrize(("scenario_name", "seed"), CASES)
@pytest.mark.parametrize("solver", ["ipopt", "fatrop"])
def test_peer_reaches_our_optimum(peers, solver, scenario_name, seed):
    scenario = get_scenario(scenario_name)
    problem = scenario.sample(np.random.default_rng(seed))
    module = peers[solver]
    peer = getattr(module, f"{solver.capitalize()}Peer")(scenario)
    rel, full = peer.solve(problem)
    _, scp = solve_problem(scenario, problem)
    assert rel.ok and full.ok
    assert scenario.cost(full.U) == pytest.approx(scp.cost, rel=1e-3)
    assert scenario.cost(full.U) > scenario.cost(rel.U) * (1 + 1e-3)  # the keep-out constraints were active
    # the trajectory is the scenario's own: dynamics, endpoints, keep-out zones
    X_sim = [problem.x0]
    for k, u in enumerate(full.U):
        X_sim.append(scenario.step(problem, k, X_sim[-1], u))
    np.testing.assert_allclose(full.X, np.array(X_sim), atol=1e-6)
    np.testing.assert_allclose(full.X[-1], problem.goal, atol=1e-6)
    assert not scenario.violations(problem, full.X).any()
    if solver == "fatrop":  # posed stage-wise: fatrop detected N = 100 stages of 6 states
        stats = peer.full.opti.stats()
        assert stats["N"] == 100
        assert list(stats["nx"])[1:] == [6] * 100
