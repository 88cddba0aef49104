"""The scenarios as gymnasium environments (``ttompc.envs``): ``check_env`` passes for the three registered ones,
the reward is minus the stage cost, the episode ends after N controls with ``goal_reached``, ``reset(seed=...)``
samples the scenario's problems, the perturbed plant perturbs, any scenario goes through ``make_env``, and
importing ttompc does not import gymnasium."""

from __future__ import annotations

import subprocess
import sys
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import ttompc.envs
from ttompc.envs import ENV_IDS, control_bounds, make_env
from ttompc.errors import UserError
from ttompc.scenarios import get_scenario


@pytest.mark.parametrize("env_id", list(ENV_IDS))
def test_check_env_passes(env_id: str) -> None:
    env = gymnasium.make(env_id)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # RPOD's unbounded action Box is warned about, not an error
        check_env(env.unwrapped)
    assert env.unwrapped.scenario.name == ENV_IDS[env_id]


def test_spaces_and_bounds() -> None:
    quad = gymnasium.make("ttompc/Quadrotor-v1")
    assert quad.observation_space.shape == (6,) and quad.action_space.shape == (3,)
    np.testing.assert_array_equal(quad.action_space.high, [10.0] * 3)  # the quadrotor's control box, U_MAX
    np.testing.assert_array_equal(quad.action_space.low, [-10.0] * 3)
    rpod = get_scenario("rpod")
    low, high = control_bounds(rpod, rpod.sample(np.random.default_rng(0)))
    assert np.all(low == -np.inf) and np.all(high == np.inf)  # RPOD's impulses have no bound


def test_freeflyer_action_box_is_its_thruster_bound_over_all_headings() -> None:
    """The free-flyer's box holds every impulse its heading-dependent thruster bound allows, and no smaller box
    does: each face is reached by an allowed impulse at some heading."""
    from ttompc.scenarios.freeflyer import DV_MAX, thruster_dv

    env = gymnasium.make("ttompc/FreeFlyer-v1")
    box = env.action_space
    assert isinstance(box, gymnasium.spaces.Box)
    low, high = box.low, box.high
    assert np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low < high)
    rng = np.random.default_rng(0)
    psi, a = rng.uniform(-np.pi, np.pi, 20000), rng.uniform(2 * low, 2 * high, (20000, 3))
    # scaled onto the bound (the allowed set is a polytope through 0 at every heading), then just inside it
    a *= (1 - 1e-9) * DV_MAX / np.abs(thruster_dv(psi, a)).max(axis=1, keepdims=True)
    assert np.all((low <= a) & (a <= high))
    faces = [(np.pi / 4, [high[0], 0, 0]), (np.pi / 4, [0, high[1], 0]), (0.0, [0, 0, high[2]])]
    for heading, u in faces:
        assert np.abs(thruster_dv(np.array(heading), np.array(u))).max() == pytest.approx(DV_MAX)
    wrapped = gymnasium.wrappers.RescaleAction(env, -np.ones(3), np.ones(3))  # wrappers that need a finite box
    wrapped.reset(seed=0)
    wrapped.step(np.ones(3))


def test_episode_reward_info_and_end() -> None:
    env = gymnasium.make("ttompc/Quadrotor-v1")
    obs, info = env.reset(seed=3)
    problem = info["problem"]
    np.testing.assert_array_equal(obs, problem.x0)
    sc = env.unwrapped.scenario
    u = np.array([1.0, -2.0, 0.5])
    total, steps = 0.0, 0
    terminated = False
    x = problem.x0
    while not terminated:
        obs, reward, terminated, truncated, info = env.step(u)
        x = sc.step(problem, steps, x, u)  # the nominal plant is the exact dynamics
        np.testing.assert_array_equal(obs, x)
        assert reward == pytest.approx(-0.5 * (1 + 4 + 0.25)) and not truncated  # ½‖u‖² by hand
        assert info["violation"] >= 0.0 and ("goal_reached" in info) == terminated
        total += reward
        steps += 1
    assert steps == problem.n_steps == info["t"]
    assert total == pytest.approx(-sc.cost(np.tile(u, (steps, 1))))
    assert info["goal_reached"] is False and info["terminal_error"] == pytest.approx(np.linalg.norm(x - problem.goal))
    with pytest.raises(UserError, match="outside an episode"):
        env.unwrapped.step(u)


def test_reset_samples_problems_by_seed_and_perturbed_plant_perturbs() -> None:
    env = gymnasium.make("ttompc/FreeFlyer-v1", plant="perturbed")
    a, info_a = env.reset(seed=7)
    b, _ = env.reset(seed=7)
    c, _ = env.reset(seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    env.reset(seed=7)
    u = np.zeros(3)
    x1 = env.step(u)[0]
    exact = env.unwrapped.scenario.step(info_a["problem"], 0, a, u)
    assert not np.allclose(x1, exact, atol=1e-9)  # process noise on the perturbed plant
    nominal = gymnasium.make("ttompc/FreeFlyer-v1")
    nominal.reset(seed=7)
    np.testing.assert_array_equal(nominal.step(u)[0], exact)
    with pytest.raises(UserError, match="unknown plant"):
        make_env("freeflyer", plant="bumpy")


def test_any_scenario_through_make_env(toy: object) -> None:
    env = make_env(toy)  # type: ignore[arg-type]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(env)
    obs, info = env.reset(seed=0)
    assert obs.shape == (env.scenario.state_dim,) and info["problem"].n_steps == env.scenario.n_steps
    given = env.scenario.sample(np.random.default_rng(5))
    obs, info = env.reset(options={"problem": given})
    assert info["problem"] is given
    with pytest.raises(UserError, match="start and goal of shape"):
        env.reset(options={"problem": type(given)(np.zeros(9), np.zeros(9), given.dt, given.n_steps)})


def test_bad_action_is_one_line() -> None:
    env = make_env("quadrotor")
    env.reset(seed=0)
    for bad in (np.zeros(2), np.array([np.nan, 0.0, 0.0]), np.array(["a", "b", "c"]), np.zeros(3) + 1j):
        with pytest.raises(UserError, match=r"finite real array of shape \(3,\)"):
            env.step(bad)
    assert env.t == 0


def test_importing_ttompc_does_not_import_gymnasium() -> None:
    code = "import sys, ttompc, ttompc.mpc; assert 'gymnasium' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)
    assert ttompc.envs.ScenarioEnv is make_env("rpod").__class__
