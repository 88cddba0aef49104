"""The scenarios as gymnasium environments (``ScenarioEnv``, ``make_env`` for any scenario). Importing this package
registers the shipped ones. gymnasium is imported here, not by ``import ttompc`` (its import takes 0.3 s on the
project's 2-core machine; ``import ttompc`` stays free of it, as of torch and Lightning):

    import gymnasium, ttompc.envs
    env = gymnasium.make("ttompc/Quadrotor-v1", plant="perturbed")   # also ttompc/FreeFlyer-v1, ttompc/RPOD-v1

or, without the import, ``gymnasium.make("ttompc.envs:ttompc/Quadrotor-v1")``.
"""

from __future__ import annotations

import gymnasium

from ttompc.envs.scenario_env import ScenarioEnv, control_bounds, make_env

ENV_IDS = {"ttompc/FreeFlyer-v1": "freeflyer", "ttompc/Quadrotor-v1": "quadrotor", "ttompc/RPOD-v1": "rpod"}

for _id, _scenario in ENV_IDS.items():
    if _id not in gymnasium.registry:
        gymnasium.register(_id, entry_point="ttompc.envs.scenario_env:ScenarioEnv", kwargs={"scenario": _scenario})

__all__ = ["ENV_IDS", "ScenarioEnv", "control_bounds", "make_env"]
