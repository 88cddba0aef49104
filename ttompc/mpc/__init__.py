"""Receding-horizon control: one loop (``run_mpc``) on an exact or perturbed plant (``plant``), its settings and
their named presets (``MPCSettings``, ``protocol_settings``), pluggable warm-start and terminal-target providers
(REL-MPC, DIST-MPC, TTO-MPC, PLAN-ONCE, ORACLE-MPC) and an episode's feasibility (``episode_metrics``; summaries
over episodes are ``ttompc.evaluation.episodes``). Importing this package does not import Lightning (nor torch until
TTO is used)."""

from ttompc.mpc.loop import (
    Episode,
    EpisodeStart,
    MPCController,
    MPCRun,
    StepPlan,
    episode_metrics,
    run_mpc,
    run_mpc_batch,
)
from ttompc.mpc.plant import Plant, PlantNoise
from ttompc.mpc.providers import (
    DISTProvider,
    OracleProvider,
    PlanProvider,
    Provider,
    RELProvider,
    RemainingREL,
    ShiftProvider,
    TerminalDesign,
    WarmStart,
)
from ttompc.mpc.settings import MPCSettings, protocol_settings
from ttompc.mpc.tto import RolloutGroup, TTOProvider, tracking_design, tto_providers

__all__ = [
    "DISTProvider",
    "Episode",
    "EpisodeStart",
    "MPCController",
    "MPCRun",
    "MPCSettings",
    "OracleProvider",
    "PlanProvider",
    "Plant",
    "PlantNoise",
    "Provider",
    "RELProvider",
    "RemainingREL",
    "RolloutGroup",
    "ShiftProvider",
    "StepPlan",
    "TTOProvider",
    "TerminalDesign",
    "WarmStart",
    "episode_metrics",
    "protocol_settings",
    "run_mpc",
    "run_mpc_batch",
    "tracking_design",
    "tto_providers",
]
