"""Receding-horizon control: one loop (``run_mpc``) on an exact or perturbed plant (``plant``), its settings and
their named presets (``MPCSettings``, ``protocol_settings``), pluggable warm-start and terminal-target providers
(REL-MPC, DIST-MPC, TTO-MPC, PLAN-ONCE, ORACLE-MPC), the closed-loop methods built from them (``METHODS``), the
terminal terms and rtg modes the settings name (``TERMINALS``, ``RTG_MODES``) and an episode's record and
feasibility (``Episode``, ``episode_metrics``; summaries over episodes are ``ttompc.evaluation.episodes``), and
DAgger's expert (``expert``: the full-horizon SCP from the measured state that labels fine-tuning's rollouts). Importing
this package does not import Lightning (nor torch until TTO is used)."""

from ttompc.mpc.departures import departures
from ttompc.mpc.episode import Episode, episode_metrics
from ttompc.mpc.loop import (
    EpisodeStart,
    MPCController,
    MPCRun,
    StepHook,
    StepPlan,
    run_mpc,
    run_mpc_batch,
)
from ttompc.mpc.methods import METHODS, Method, MethodInputs, methods_for
from ttompc.mpc.plant import Plant, PlantNoise
from ttompc.mpc.providers import (
    DISTProvider,
    OracleProvider,
    PlanProvider,
    Provider,
    RELProvider,
    RemainingREL,
    ShiftProvider,
    WarmStart,
)
from ttompc.mpc.rtg import RTG_MODES, RTGFeed
from ttompc.mpc.settings import MPCSettings, protocol_settings
from ttompc.mpc.terminal import TERMINALS, TargetFilter, TerminalDesign, TerminalTerm
from ttompc.mpc.tto import RolloutGroup, TTOProvider

__all__ = [
    "METHODS",
    "RTG_MODES",
    "TERMINALS",
    "DISTProvider",
    "Episode",
    "EpisodeStart",
    "MPCController",
    "MPCRun",
    "MPCSettings",
    "Method",
    "MethodInputs",
    "OracleProvider",
    "PlanProvider",
    "Plant",
    "PlantNoise",
    "Provider",
    "RELProvider",
    "RTGFeed",
    "RemainingREL",
    "RolloutGroup",
    "ShiftProvider",
    "StepHook",
    "StepPlan",
    "TTOProvider",
    "TargetFilter",
    "TerminalDesign",
    "TerminalTerm",
    "WarmStart",
    "departures",
    "episode_metrics",
    "methods_for",
    "protocol_settings",
    "run_mpc",
    "run_mpc_batch",
]
