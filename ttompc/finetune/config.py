"""Typed DAgger fine-tuning recipe (``recipes/<scenario>/finetune*.yaml``): ``dagger`` plus the training sections
``data``, ``optim``, ``trainer``, ``logger`` and ``callbacks`` (``model`` comes from the pretrained model).

Every key a recipe may set is used. The ``trainer`` section is pre-training's ``TrainerConfig`` less the keys
DAgger owns (``DAGGER_OWNED``): DAgger sets the step budget itself (``dagger.steps_per_iteration`` per iteration,
continuing from the parent's global step), always resumes (``dagger_state.json``), keeps one checkpoint per
iteration and always exports the selected planner, so a recipe or override that sets ``max_steps``, ``max_epochs``,
``keep_checkpoints``, ``resume`` or ``export_planner`` is rejected. A fine-tuning names its MPC settings once, in
its keep/reject measurement ``dagger.eval`` (a ``ttompc.evaluation.measurement.Measurement``): ``dagger.eval.protocol``
(a preset of ``ttompc.mpc.settings`` or a YAML file) with single-key overrides in ``dagger.eval.mpc``. The rollouts
take every setting from it but those they cannot run (``check_rollout_settings``: refused when the recipe loads),
and the training callback measures under it too (a recipe that sets ``callbacks.eval_mpc.protocol`` or
``callbacks.eval_mpc.mpc`` is rejected). The open-loop/closed-loop mix is ``data.open_loop_fraction``
with ``data.closed_loop_share``: "grow" is the paper's (9:1 at the first iteration, then the closed-loop share grows
as DAgger data accumulates), "fixed" keeps that fraction at every iteration.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from ttompc.config import ConfigError, given_keys, load_command_config
from ttompc.data.config import DataConfig
from ttompc.evaluation.measurement import Measurement
from ttompc.mpc.rtg import RTG_MODES
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.terminal import TERMINALS
from ttompc.ranges import Checked, setting
from ttompc.training.config import CallbacksConfig, LoggerConfig, OptimConfig, TrainerConfig

DAGGER_OWNED = ("max_steps", "max_epochs", "keep_checkpoints", "resume", "export_planner")  # trainer keys DAgger sets
# keys dagger.eval sets for the callback
MEASURED_ONCE = ("callbacks.eval_mpc.protocol", "callbacks.eval_mpc.robust_blend", "callbacks.eval_mpc.mpc")


@dataclass
class ExplorationConfig(Checked):
    """Exploration policy of a rollout (paper Alg. 1, §IV-C): the learner is TTO-MPC with H drawn
    uniformly from ``horizons``; the expert acts inside ``windows`` = U{min..max} windows of U{min..max} steps,
    one of them covering the end of the episode when ``end_window``."""

    horizons: list[int] = setting(factory=lambda: list(range(10, 101, 10)), ge=1, nonempty=True, unique=True)
    windows: list[int] = setting(factory=lambda: [1, 3], ge=0)
    window_length: list[int] = setting(factory=lambda: [15, 25], ge=0)
    end_window: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("windows", "window_length"):
            lo_hi = getattr(self, name)
            if len(lo_hi) != 2 or lo_hi[0] > lo_hi[1]:
                raise ValueError(f"dagger.exploration.{name} must be [min, max] with 0 <= min <= max, got {lo_hi}")


@dataclass
class LabelConfig(Checked):
    """Which visited states get an expert label, and what a label is (``ttompc.finetune.collect``).

    ``per_rollout``: labelled visited steps per rollout, drawn without replacement (0: every step, the paper); steps
    where the expert acts are labelled too. The loss skips unlabelled steps (a departure when > 0: the expert's
    full-horizon solve at every visited state is most of a rollout's cost, docs/scaling.md). ``late`` tilts the draw
    toward the end of the episode, where the closed loop fails (weights exp(late · t/(N − 1)); 0: uniform).
    ``kind``: ``step`` (the paper) labels the visited state x_t with the expert's control u*_t and f(x_t, u*_t), one
    row per rollout; ``plan`` (a departure) writes one row per labelled step: the visited prefix up to x_t followed by
    the expert's whole plan from x_t, so the model learns the plan it should generate from where the learner is.
    ``rtg`` (plan rows): the reward-to-go from x_t on, ``learner`` (the learner's running value, run on by the plan's
    stage costs) or ``expert`` (the plan's own cost-to-go, as open-loop rows carry; measured in docs/scaling.md)."""

    kind: Literal["step", "plan"] = "step"
    per_rollout: int = setting(0, ge=0, meaning="0: every step")
    rtg: Literal["learner", "expert"] = "learner"
    # at most 100, the first step e^-100 as likely as the last: the draw is the last steps' alone long before e^late
    # overflows float64 (late ~ 710), which would leave it no weights
    late: float = setting(0.0, ge=0, le=100, meaning="0: uniform")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.kind not in ("step", "plan"):
            raise ValueError(f"dagger.labels.kind must be 'step' or 'plan', got {self.kind!r}")
        if self.rtg not in ("learner", "expert"):
            raise ValueError(f"dagger.labels.rtg must be 'learner' or 'expert', got {self.rtg!r}")


@dataclass
class CollectConfig(Checked):
    rollouts: int = setting(2000, ge=1)  # closed-loop rollouts per iteration (all ranks together)
    workers: int = setting(0, ge=0, per_core=4, meaning="0: all cores")  # processes per rank (spawn pool)
    shard_size: int = setting(50, ge=1)  # rollouts per shard (the unit of resumption and of the rank split)
    batch: int = setting(10, ge=1)  # rollouts a worker runs in lockstep (one batched transformer rollout per step)
    val_fraction: float = setting(0.1, ge=0, lt=1)  # share of rollouts written to the DAgger val split (by hash)
    # share of rollouts run on the evaluations' perturbed plant (``PlantNoise.perturbed``), each drawn from its own
    # seed: the disturbed states are where re-planning from the measured state fails; 0 = the exact plant (paper)
    perturbed: float = setting(0.0, ge=0, le=1)
    wait_s: float = setting(3600.0, ge=0)  # multi-rank: how long to wait for other ranks' shards and rank 0's decisions


# MPCSettings values DAgger's rollouts cannot run (``check_rollout_settings``), each with why: the value they run
# and the reason (measure the others with `ttompc evaluate mpc`)
ROLLOUT_FIXED: dict[str, tuple[Any, str]] = {
    # the learners, asking windows of their own H, share one decode schedule: a rollout's plans would depend on the
    # other rollouts of its batch, not be its lone run's
    "decode_every": (1, "their learners decode at every step"),
}


def check_rollout_settings(settings: MPCSettings) -> None:
    """Refuse, in one line naming the keys, the settings DAgger's rollouts cannot honour: ``ROLLOUT_FIXED``'s, and a
    terminal term or rtg mode that declares it cannot run in them (``TerminalTerm.rollouts``, ``RTGFeed.rollouts``);
    they take every other key (``ttompc.finetune.collect.collect_rollouts``). Raises ``ConfigError``."""
    fixed = [k for k, (v, _) in ROLLOUT_FIXED.items() if getattr(settings, k) != v]
    runnable = {  # the terminal terms and rtg modes the rollouts run
        "terminal": [name for name, kind in TERMINALS.items() if kind.rollouts],
        "rtg_mode": [name for name, mode in RTG_MODES.items() if mode.rollouts],
    }
    refused = [k for k, names in runnable.items() if getattr(settings, k) not in names]
    if fixed or refused:
        given = " ".join(f"{k}={json.dumps(getattr(settings, k))}" for k in fixed + refused)
        why = [ROLLOUT_FIXED[k][1] for k in fixed] + [f"the {k} declares they cannot run it" for k in refused]
        fix = [f"dagger.eval.mpc.{k}={json.dumps(ROLLOUT_FIXED[k][0])}" for k in fixed]
        fix += [f"dagger.eval.mpc.{k} among {runnable[k]}" for k in refused]
        raise ConfigError(
            f"dagger.eval: DAgger's rollouts cannot run {given} ({'; '.join(why)})",
            f"use {' '.join(fix)}, and measure it with `ttompc evaluate mpc`",
        )


@dataclass
class DaggerConfig(Checked):
    iterations: int = setting(10, ge=1)
    seed: int = setting(0, ge=0)  # root seed: rollout (i, r) uses SeedSequence(seed, spawn_key=(stream, i, r))
    steps_per_iteration: int = setting(3000, ge=1)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    labels: LabelConfig = field(default_factory=LabelConfig)
    collect: CollectConfig = field(default_factory=CollectConfig)
    # the keep/reject measurement (closed-loop TTO-MPC on fixed held-out problems, one horizon on one plant, before
    # iteration 0 and after every iteration: ``ttompc.finetune.loop.improves``); its protocol and ``mpc`` overrides
    # are the MPC settings of the rollouts and of every closed loop of the run (the zoo's cards report zoo, so the
    # decision can be made under the settings the cards report, docs/evaluation.md)
    eval: Measurement = field(default_factory=lambda: Measurement(problems=4))

    def __post_init__(self) -> None:
        super().__post_init__()
        self.eval.check_single("dagger.eval")
        check_rollout_settings(self.eval.settings)


@dataclass
class FinetuneConfig:
    dagger: DaggerConfig = field(default_factory=DaggerConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=3e-5, warmup_steps=0))
    trainer: TrainerConfig = field(
        default_factory=lambda: TrainerConfig(checkpoint_every_n_steps=100, out_dir="runs/freeflyer-dagger")
    )  # checkpoint_every_n_steps refreshes checkpoints/iter-<i>.ckpt: an interrupted iteration resumes there
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    # closed-loop TTO-MPC of the model being fine-tuned, logged at its validation runs (``ClosedLoopEvalCallback``),
    # under dagger.eval's protocol and overrides (filled in here; a recipe that sets them is refused)
    callbacks: CallbacksConfig = field(default_factory=CallbacksConfig)

    def __post_init__(self) -> None:
        if self.data.dagger_dirs:
            raise ValueError(
                "data.dagger_dirs is filled by DAgger itself (<out_dir>/dagger/iter-*); leave it empty in a "
                f"fine-tuning recipe, got {list(self.data.dagger_dirs)}"
            )
        m = self.dagger.eval
        self.callbacks.eval_mpc = replace(
            self.callbacks.eval_mpc, protocol=m.protocol, mpc=dict(m.mpc), robust_blend=m.robust_blend
        )


def load_finetune_config(path: str | Path | None = None, overrides: Sequence[str] = ()) -> FinetuneConfig:
    """Load and validate a fine-tuning recipe (schema <- YAML <- ``key=value`` overrides); a trainer key DAgger owns
    (``DAGGER_OWNED``) is an error."""
    try:
        cfg = load_command_config(FinetuneConfig, path, overrides)
    except ConfigError:
        raise
    except ValueError as err:
        raise ConfigError(f"invalid config ({path or 'defaults'}): {err}") from None
    given = given_keys(path, overrides)
    owned = sorted(f"trainer.{k}" for k in DAGGER_OWNED if f"trainer.{k}" in given)
    if owned:
        raise ConfigError(
            f"{', '.join(owned)}: set by DAgger itself", "size iterations with dagger.steps_per_iteration instead"
        )
    shared = sorted(k for k in given if k in MEASURED_ONCE or k.startswith(f"{MEASURED_ONCE[-1]}."))
    if shared:
        raise ConfigError(
            f"{', '.join(shared)}: a fine-tuning names its MPC settings once, in dagger.eval",
            "set dagger.eval.protocol and dagger.eval.mpc.KEY instead (the rollouts and every measurement use them)",
        )
    return cfg
