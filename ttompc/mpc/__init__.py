"""Receding-horizon control: one loop (``run_mpc``) with pluggable warm-start/terminal-target providers
(REL-MPC, DIST-MPC, TTO-MPC). Importing this package does not import Lightning (nor torch until TTO is used)."""

from ttompc.mpc.loop import Episode, MPCController, StepPlan, episode_metrics, run_mpc
from ttompc.mpc.providers import DISTProvider, Provider, RELProvider, ShiftProvider, TTOProvider, WarmStart

__all__ = [
    "DISTProvider",
    "Episode",
    "MPCController",
    "Provider",
    "RELProvider",
    "ShiftProvider",
    "StepPlan",
    "TTOProvider",
    "WarmStart",
    "episode_metrics",
    "run_mpc",
]
