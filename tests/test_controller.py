"""``ttompc.Controller``: the episode it drives on our plant is exactly ``evaluate mpc``'s (controls and cost, every
method, nominal and perturbed plant), bad input is one ``UserError`` line that leaves it usable, a failed window
applies the fallback control, and its steps compile nothing (the warm-up ran before step 0)."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ttompc.errors import UserError
from ttompc.evaluation import closed_loop
from ttompc.evaluation.closed_loop import ClosedLoopConfig, run_problems
from ttompc.mpc.controller import Controller, sample_problem
from ttompc.mpc.plant import Plant
from ttompc.policy import Planner
from ttompc.scenarios import get_scenario

MODEL = Path(__file__).parents[1] / "zoo" / "models" / "quadrotor-ft-tto-v6"


@pytest.fixture(scope="module")
def planner() -> Planner:
    return Planner.from_pretrained(MODEL)


def test_an_episode_is_the_same_alone_or_in_a_batch(planner: Planner) -> None:
    """R-TTO-MPC in lockstep: each episode of a batch of two equals the same problem run alone (the robust target's
    memory is one episode's, never shared across the batch); equal to the batched rollout's rounding (~1e-8)."""
    from ttompc.evaluation.episodes import closed_loop_metrics
    from ttompc.evaluation.measurement import Measurement

    m = Measurement(
        protocol="recommended",
        problems=2,
        seed=4242,
        horizons=[10],
        plants=["nominal"],
        max_steps=12,
        robust_blend=0.95,
    )
    problems = m.problem_set(planner.scenario)
    _, batch = closed_loop_metrics(planner, m, problems)
    for ep, together in zip(problems, batch, strict=True):
        _, [alone] = closed_loop_metrics(planner, m, [ep])
        np.testing.assert_allclose(alone.U, together.U, rtol=0, atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("plant", ["nominal", "perturbed"])
def test_controller_reproduces_evaluate_mpc(planner: Planner, plant: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """One problem (evaluate mpc's batch of one): every method's controls and cost through the Controller on our
    plant equal the episode ``evaluate mpc`` runs."""
    sc = planner.scenario
    cfg = ClosedLoopConfig(
        ft_model=str(MODEL),
        scenario=sc.name,
        protocol="recommended",
        problems=1,
        seed=4242,
        horizons=[10],
        plants=[plant],
        batch=1,
    )
    [ep] = cfg.problem_set(sc)
    seen: list[Any] = []

    def capture(*args: Any, **kwargs: Any) -> Any:
        episodes = run_batch(*args, **kwargs)
        seen.extend(episodes)
        return episodes

    run_batch = closed_loop.run_mpc_batch
    monkeypatch.setattr(closed_loop, "run_mpc_batch", capture)
    records = run_problems(sc, [ep], {"FT-TTO": planner}, cfg)
    [(_, run)] = cfg.runs(sc)
    assert len(seen) == len(records) >= 6
    for episode, record in zip(seen, records, strict=True):
        method = episode.method.split("[")[0]
        ctrl = Controller(sc, method, planner=planner, horizon=10, protocol="recommended")
        ctrl.reset(ep.problem)  # as a user would: J_REL solved by the Controller for a learned method
        assert ctrl.method.model is None or ctrl.rel_cost == ep.rel_cost
        sim = Plant(sc, run.plant)
        sim.reset(ep.seed)
        x, U = ep.problem.x0.copy(), []
        for t in range(ep.problem.n_steps):
            U.append(ctrl.step(x))
            x = sim.step(ep.problem, t, x, U[-1])
        assert ctrl.name == episode.method
        np.testing.assert_array_equal(np.array(U), episode.U, err_msg=episode.method)
        assert sc.cost(np.array(U)) == record["cost"] == episode.cost


def test_step_record(planner: Planner) -> None:
    ctrl = Controller.from_pretrained(MODEL, horizon=5)
    assert ctrl.name.startswith("R-FT-TTO-MPC")  # the model is fine-tuned: its robust method by default
    problem = sample_problem(ctrl.scenario, np.random.default_rng(0))
    ctrl.reset(problem)
    assert ctrl.rel_cost > 0  # J_REL solved at reset for a learned method
    u = ctrl.step(problem.x0)
    rec = ctrl.last
    assert rec is not None and rec.t == 0 and ctrl.t == 1
    np.testing.assert_array_equal(rec.u, u)
    np.testing.assert_array_equal(rec.U[0], u)
    assert rec.X.shape == (6, 6) and rec.U.shape == (5, 3) and rec.target is not None
    assert rec.status in ("converged", "feasible") and rec.iterations >= 1
    assert rec.seconds >= rec.warm_time + rec.solve_time and rec.observe_time == 0.0
    x1 = problem.x0 + 0.01  # any measured state: the controller plans from it
    ctrl.step(x1)
    assert ctrl.last is not None and ctrl.last.t == 1 and ctrl.last.observe_time > 0
    np.testing.assert_array_equal(ctrl.last.X[0], x1)


def _bad(call: Any, match: str) -> None:
    with pytest.raises(UserError, match=match) as err:
        call()
    assert "\n" not in str(err.value)


def test_bad_input_is_one_line_and_leaves_the_controller_usable(planner: Planner) -> None:
    sc = planner.scenario
    _bad(lambda: Controller(sc, "MAGIC-MPC"), "unknown method 'MAGIC-MPC'")
    _bad(lambda: Controller("nonesuch"), "nonesuch")
    _bad(lambda: Controller(sc, horizon=0), r"horizon must be an integer in \[1, 100\]")
    _bad(lambda: Controller(sc, horizon=10.5), r"horizon must be an integer .* got 10.5")  # type: ignore[arg-type]
    _bad(lambda: Controller(sc, "R-TTO-MPC"), "plans with a model")
    _bad(lambda: Controller(sc, "REL-MPC", protocol="nonesuch"), "unknown protocol 'nonesuch'")
    _bad(lambda: Controller("rpod", "R-TTO-MPC", planner=planner), "trained on 'quadrotor', not 'rpod'")
    _bad(lambda: Controller.from_pretrained(MODEL, scenario="freeflyer"), "trained on scenario 'quadrotor'")
    ctrl = Controller(sc, "REL-MPC", horizon=5)
    _bad(lambda: ctrl.step(np.zeros(6)), r"step\(\) before reset")
    problem = sample_problem(ctrl.scenario, np.random.default_rng(0))
    bad_problem = type(problem)(np.zeros(4), np.zeros(4), problem.dt, problem.n_steps)
    _bad(lambda: ctrl.reset(bad_problem), r"shape \(6,\)")
    _bad(lambda: ctrl.reset(dataclasses.replace(problem, n_steps=50)), "problems have 100 steps, got 50")
    for other in ("rpod", "freeflyer"):  # of the same shape: told apart by params and dt (``Scenario.validate``)
        theirs = sample_problem(get_scenario(other), np.random.default_rng(0))
        _bad(lambda p=theirs: ctrl.reset(p), r"^quadrotor: its problems have .*\(another scenario's problem\?\)$")
    ctrl.reset(problem)
    _bad(lambda: ctrl.step(np.zeros(5)), r"shape \(6,\), got \(5,\)")
    _bad(lambda: ctrl.step(np.full(6, np.nan)), "NaN or inf")
    _bad(lambda: ctrl.step(np.r_[problem.x0[:5], np.inf]), "NaN or inf")
    _bad(lambda: ctrl.step(np.array(["a"] * 6)), "must hold real numbers")
    _bad(lambda: ctrl.step(problem.x0 + 1j), "must hold real numbers")
    _bad(lambda: ctrl.step(problem.x0, applied=np.zeros(3)), "first step")
    assert ctrl.t == 0 and ctrl.last is None  # nothing happened
    u = ctrl.step(problem.x0)
    assert u.shape == (3,) and np.all(np.isfinite(u)) and ctrl.t == 1
    _bad(lambda: ctrl.step(problem.x0, applied=np.zeros(2)), r"applied control must have shape \(3,\)")
    assert ctrl.t == 1


def test_applied_control_reaches_the_method(planner: Planner) -> None:
    """``step(x, applied=...)``: the method observes the control that acted (TTO-MPC's spent cost counts it)."""
    ctrl = Controller(planner.scenario, "TTO-MPC", planner=planner, horizon=5)
    problem = sample_problem(ctrl.scenario, np.random.default_rng(1))
    ctrl.reset(problem)
    u = ctrl.step(problem.x0)
    half = 0.5 * u
    ctrl.step(ctrl.scenario.step(problem, 0, problem.x0, half), applied=half)
    provider = ctrl._mpc.provider if ctrl._mpc is not None else None
    assert provider is not None and provider.spent == pytest.approx(ctrl.scenario.cost(half[None]))  # type: ignore[attr-defined]


def test_a_failed_window_applies_the_fallback_and_says_so(planner: Planner, monkeypatch: pytest.MonkeyPatch) -> None:
    """A window whose SCP fails: the previous plan's next control, status "fallback", no exception."""
    from ttompc.mpc import loop
    from ttompc.solvers.scp import SCPStatus

    ctrl = Controller(planner.scenario, "REL-MPC", horizon=5)
    problem = sample_problem(ctrl.scenario, np.random.default_rng(0))
    ctrl.reset(problem)
    ctrl.step(problem.x0)
    first = ctrl.last
    assert first is not None and not first.fallback

    def failing(*args: Any, **kwargs: Any) -> Any:
        res = solve(*args, **kwargs)
        res.status, res.best_iteration = SCPStatus.INFEASIBLE, -1
        return res

    solve = loop.solve_scp
    monkeypatch.setattr(loop, "solve_scp", failing)
    x1 = planner.scenario.step(problem, 0, problem.x0, first.u)
    u = ctrl.step(x1)
    assert ctrl.last is not None and ctrl.last.fallback and "fallback" in ctrl.last.message
    np.testing.assert_array_equal(u, first.U[1])  # the previous plan's next control


_NO_COMPILE = """
import json, sys
from numba.core.dispatcher import Dispatcher
from ttompc.mpc import loop
from ttompc.mpc.controller import Controller, sample_problem
from ttompc.mpc.plant import Plant
from ttompc.scenarios.dynamics import CompiledStep
import numpy as np

def overloads():  # compiled (or cache-loaded) specialisations of ttompc's numba functions and dynamics steps
    n = 0
    for name, mod in list(sys.modules.items()):
        if name.startswith("ttompc"):
            n += sum(len(v.overloads) for v in vars(mod).values() if isinstance(v, Dispatcher))
            n += sum(len(v.dynamics._cfuncs) for v in vars(mod).values()
                     if isinstance(getattr(v, "dynamics", None), CompiledStep))  # a scenario's cfunc per dtype
    return n

if sys.argv[2] == "controller":
    ctrl = Controller.from_pretrained(sys.argv[1], horizon=10)
    problem = sample_problem(ctrl.scenario, np.random.default_rng(0))
    ctrl.reset(problem)
    before = overloads()
    x, plant = problem.x0, Plant(ctrl.scenario)
    for t in range(problem.n_steps):
        x = plant.step(problem, t, x, ctrl.step(x))
else:  # the episode loop of evaluate mpc, the callback, DAgger and the demo: counted at its first plan
    from ttompc.mpc.methods import METHODS, MethodInputs
    from ttompc.mpc.settings import protocol_settings
    from ttompc.policy import Planner
    from ttompc.solvers.scp import solve_rel

    planner = Planner.from_pretrained(sys.argv[1])
    Controller(planner.scenario)  # its warm-up covers the solver only: the decoder is left to the loop's
    problem = sample_problem(planner.scenario, np.random.default_rng(0))
    counts, plan = [], loop.MPCController.plan

    def counted(self, t, x):
        counts.append(overloads())
        return plan(self, t, x)

    loop.MPCController.plan = counted
    settings = protocol_settings("recommended")
    providers = METHODS["R-FT-TTO-MPC"].providers(MethodInputs(settings, [None], planner))
    start = loop.EpisodeStart(problem, solve_rel(planner.scenario, problem).cost)
    loop.run_mpc_batch(planner.scenario, [start], providers, loop.MPCRun(10, settings))
    before = counts[0]
print(json.dumps({"before": before, "after": overloads()}))
"""


@pytest.mark.slow
@pytest.mark.parametrize("entry", ["controller", "loop"])
def test_a_first_run_compiles_nothing_inside_a_step(entry: str) -> None:
    """In a fresh process, the Controller's construction or ``run_mpc_batch`` before its first step compiled (or
    loaded) every numba function the steps call: a whole episode adds no specialisation to any of ttompc's numba
    functions nor a compiled dynamics step (a ``CompiledStep`` cfunc) to any scenario (without the warm-up it adds
    some). A property, not a timing: so a first run's step times are a second run's."""
    cmd = [sys.executable, "-c", _NO_COMPILE, str(MODEL), entry]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["before"] > 0 and result["after"] == result["before"], result


@pytest.mark.slow
def test_control_loop_example_runs(tmp_path: Path) -> None:
    """examples/control_loop.py as the README shows it: a zoo model's learned MPC on the gymnasium quadrotor."""
    example = Path(__file__).parents[1] / "examples" / "control_loop.py"
    env = {**os.environ, "TTOMPC_HOME": str(tmp_path / "cache"), "TTOMPC_PROGRESS": "0", "HF_HUB_OFFLINE": "1"}
    out = subprocess.run([sys.executable, str(example)], capture_output=True, text=True, check=True, env=env)
    assert re.fullmatch(
        r"R-FT-TTO-MPC\[rtg=value\]: cost \d+\.\d{4}, goal reached: (True|False), step [\d.]+ ms mean, [\d.]+ ms p99",
        out.stdout.strip(),
    ), out.stdout


def test_readme_shows_the_control_loop_example() -> None:
    """The README's "Control your own system" block is examples/control_loop.py (below its docstring)."""
    root = Path(__file__).parents[1]
    readme = (root / "README.md").read_text(encoding="utf-8")
    section = readme[readme.index("## Control your own system") :]
    block = re.search(r"```python\n(.*?)```", section, re.DOTALL)
    example = (root / "examples" / "control_loop.py").read_text(encoding="utf-8")
    assert block is not None and block.group(1) == example.split('"""', 2)[2].lstrip("\n")
