"""The quadrotor's pretrained learned MPC in a gymnasium loop: python examples/control_loop.py"""

import gymnasium
import numpy as np

import ttompc
import ttompc.envs  # registers ttompc/FreeFlyer-v1, ttompc/Quadrotor-v1 and ttompc/RPOD-v1

env = gymnasium.make("ttompc/Quadrotor-v1", plant="perturbed")  # the state is observed, the control is the action
ctrl = ttompc.Controller.from_pretrained("quadrotor-ft-tto-v6", horizon=10)  # method="REL-MPC" etc. for baselines
obs, info = env.reset(seed=0)
ctrl.reset(info["problem"])  # start, goal and the scenario's extras
cost, latency, done = 0.0, [], False
while not done:
    action = ctrl.step(obs)  # one MPC step from the measured state
    latency.append(ctrl.last.seconds)  # ctrl.last: the window's plan, target, SCP iterations and status
    obs, reward, done, _, info = env.step(action)
    cost -= reward  # reward = −stage cost
mean, p99 = 1e3 * np.mean(latency), 1e3 * np.percentile(latency, 99)
print(f"{ctrl.name}: cost {cost:.4f}, goal reached: {info['goal_reached']}, step {mean:.1f} ms mean, {p99:.1f} ms p99")
