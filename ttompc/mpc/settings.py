"""``MPCSettings``: how the receding-horizon loop runs, and the named presets (protocols) that fix them.

One settings object serves every closed-loop consumer: the MPC loop (``ttompc.mpc.loop``), ``ttompc evaluate mpc``,
the closed-loop training callback and DAgger (its measurement and its rollouts), each through the one measurement
object that resolves a protocol and its overrides once (``ttompc.evaluation.measurement.Measurement``). A protocol
is a YAML file of ``MPCSettings`` keys: a shipped preset by name (``ttompc/mpc/presets/<name>.yaml``: ``paper``,
``recommended``, ``zoo``) or a path to a file of your own. Keys a file leaves out keep the ``MPCSettings``
defaults, which are the ``paper`` preset's. Commands take ``protocol=NAME`` plus single-key overrides
(``mpc.end_horizon=20``).

The terminal term and the rtg mode are names here, held by their registries (``ttompc.mpc.terminal.TERMINALS``,
``ttompc.mpc.rtg.RTG_MODES``), which sit above this module: each registers its names (``register_names``) when
imported, and importing any module of ``ttompc.mpc`` imports both first (the package's ``__init__``), so
``MPCSettings`` refuses a name its registry does not hold. The entries describe themselves: what they need of the
model, whether they depart from the paper (``ttompc.mpc.departures``, listed under every report's table) and whether
DAgger's rollouts run them. A new terminal term or rtg mode is a class in its registry's module plus the presets that
name it.
"""

from __future__ import annotations

import json
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from ttompc.policy.config import DECODERS
from ttompc.ranges import Checked, setting

if TYPE_CHECKING:
    from ttompc.scenarios.base import Scenario

Mode = Literal["soft", "hard"]
PRESETS = Path(__file__).with_name("presets")
# plan reuse: the measured state is the own plan's prediction within this many state_scale units (∞-norm). On an
# exact plant the two differ by the subproblem solver's residual of the dynamics rows (about 1e-9 here).
REUSE_TOL = 1e-6
# real-time iteration: in no window, in every controller's, in the learned methods' only, or in the learned methods'
# windows that reach the end only (MPCSettings.rti)
RTI_SCOPES: tuple[bool | str, ...] = (False, True, "model", "end")
# what a provider's plans are (``Provider.role``), the one thing of a provider the RTI and end-shift rules read: a
# learned model's, a baseline's (solved), or the expert's (labels, ``ttompc.mpc.expert``)
Role = Literal["learned", "baseline", "expert"]
# setting -> the names it takes, as their registries hold them (``register_names``: terminal, rtg_mode)
NAMES: dict[str, Collection[str]] = {}


def register_names(key: str, names: Collection[str]) -> None:
    """Make the names in ``names`` (a registry, read when a setting is checked) the values ``MPCSettings.<key>``
    takes."""
    if key not in MPCSettings.__dataclass_fields__:
        raise ValueError(f"MPCSettings has no setting {key!r}")
    NAMES[key] = names


@dataclass
class MPCSettings(Checked):
    """The settings of a closed-loop run (``ttompc.mpc.loop`` documents each behaviour).

    ``mode``: soft (all paper analyses) or hard end condition. ``end_horizon``: windows run to N once N − t <=
    end_horizon (0: the paper's fixed H, windows truncated at N; None: the scenario's ``mpc.end_horizon``, measured
    per scenario, ``end_horizon_on``). ``track``: terminal weight of the plan-tracking providers (TTO-MPC,
    PLAN-ONCE, ORACLE-MPC); None: the scenario's ``mpc.tracking``. ``terminal``: the kind of their terminal term
    (``ttompc.mpc.terminal.TERMINALS``). ``rtg_mode``: the reward-to-go TTO-MPC feeds in closed loop
    (``ttompc.mpc.rtg.RTG_MODES``). ``reuse``: plan reuse in windows that reach the end (same results; False
    re-solves every step). ``end_shift``: a learned method's end window starts from its previous plan's tail instead
    of its provider's warm start (``shift_for``). ``rti``: real-time iteration, one SCP subproblem per step: True in
    every controller's windows, ``"model"`` in the windows of the methods that plan from a learned model only
    (TTO-MPC and its variants, ``Provider.role``; the baselines REL-MPC, DIST-MPC, PLAN-ONCE and ORACLE-MPC then
    solve every window to convergence, as the paper's), ``"end"`` in those methods' windows that reach the end only,
    False in none; None: the scenario's own scope (``mpc.rti``, measured per scenario, as ``track``). ``rti_for`` is
    the one rule that decides a controller; DAgger's expert never runs RTI. ``decode_every``: TTO-MPC decodes a plan
    from its model every k steps and serves the windows in between from slices of it
    (``ttompc.mpc.tto.RolloutGroup``; 1: the paper's, a decode at every step). ``backend``: the QP/cone backend of
    every solve (``ttompc.solvers.backends``). ``decoder``: how TTO-MPC's rollouts decode
    (``ttompc.policy.config.DECODERS``): "torch" (eager ops), "fused" (one compiled call per rollout,
    ``ttompc.policy.fused``: the same plans up to float rounding; refused for a model or scenario it cannot run) or
    "auto" (fused where it can, else torch with a warning)."""

    mode: Mode = "soft"
    end_horizon: int | None = setting(0, ge=0, meaning="0: the paper's fixed H; None: the scenario's")
    track: float | None = setting(None, gt=0)
    terminal: str = "target"
    rtg_mode: str = "running"
    reuse: bool = True
    end_shift: bool = False
    rti: bool | str | None = False  # False, True, "model" or "end" (RTI_SCOPES); None: the scenario's mpc.rti
    decode_every: int = setting(1, ge=1, meaning="1: a decode at every step")
    backend: str = "auto"
    decoder: str = "torch"

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.mode not in ("soft", "hard"):
            raise ValueError(f"mode must be 'soft' or 'hard', got {self.mode!r}")
        for key, names in NAMES.items():
            if getattr(self, key) not in names:
                raise ValueError(f"{key} must be one of {list(names)}, got {getattr(self, key)!r}")
        if self.rti is not None and self.rti not in RTI_SCOPES:
            raise ValueError(f"rti must be one of {RTI_SCOPES}, got {self.rti!r}")
        if self.decoder not in DECODERS:
            raise ValueError(f"decoder must be one of {list(DECODERS)}, got {self.decoder!r}")

    def rti_scope(self, scenario: Scenario) -> bool | str:
        """The real-time-iteration scope on ``scenario``: ``rti``, or the scenario's ``mpc.rti`` where it is None
        (the scenario states its measured scope, the settings choose it or defer to it)."""
        scope = scenario.mpc.rti if self.rti is None else self.rti
        if scope not in RTI_SCOPES:
            raise ValueError(f"{scenario.name}: mpc.rti must be one of {RTI_SCOPES}, got {scope!r}")
        return scope

    def end_horizon_on(self, scenario: Scenario) -> int:
        """The end horizon on ``scenario``: ``end_horizon``, or the scenario's ``mpc.end_horizon`` where it is None
        (a negative one raises ``ValueError`` naming the scenario)."""
        k = scenario.mpc.end_horizon if self.end_horizon is None else self.end_horizon
        if k < 0:
            raise ValueError(f"{scenario.name}: mpc.end_horizon must be >= 0, got {k}")
        return k

    def rti_for(self, role: Role, scenario: Scenario) -> bool | str:
        """Where a controller on ``scenario`` whose provider has ``role`` runs real-time iteration: True (in every
        window), "end" (in its windows that reach the end) or False; the one rule, which ``MPCController`` applies
        and nothing overrides. The expert never does (its plans are labels); in ``rti_scope``'s scope True every
        other controller does, in "model" and "end" the learned ones only."""
        scope = self.rti_scope(scenario)
        if role == "expert" or scope is False or (scope is not True and role != "learned"):
            return False
        return "end" if scope == "end" else True

    def shift_for(self, role: Role) -> bool:
        """Whether a controller whose provider has ``role`` starts its end windows from its own previous plan
        (``end_shift``, ``ttompc.mpc.loop``): under ``end_shift`` the learned methods' only. A baseline's warm start
        is part of its method (REL-MPC: the remaining-horizon REL), and the expert's plans are labels."""
        return self.end_shift and role == "learned"

    @property
    def reuse_tol(self) -> float | None:
        """The plan-reuse tolerance of the loop (None: re-solve every step)."""
        return REUSE_TOL if self.reuse else None


def preset_names() -> list[str]:
    """The shipped presets, by name."""
    return sorted(p.stem for p in PRESETS.glob("*.yaml"))


def protocol_settings(protocol: str, overrides: Mapping[str, Any] | None = None) -> MPCSettings:
    """The settings of ``protocol`` (a preset name or a YAML file) with ``overrides`` (key -> value) on top; raises
    ``ttompc.config.ConfigError`` naming the protocol or key that does not fit."""
    from ttompc.config import ConfigError, load_command_config

    path = PRESETS / f"{protocol}.yaml" if protocol in preset_names() else Path(protocol)
    if not path.is_file():
        raise ConfigError(f"unknown protocol {protocol!r}", f"use one of {preset_names()} or a YAML file of settings")
    dotlist = [f"{key}={json.dumps(value)}" for key, value in (overrides or {}).items()]  # JSON values are YAML
    return load_command_config(MPCSettings, path, dotlist)
