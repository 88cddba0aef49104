"""``ttompc evaluate loss``: a model's training objective on the splits of given datasets, open-loop (REL/SCP) rows
and DAgger (closed-loop) rows apart, so that a model that cannot fit (training and held-out loss both high) is told
apart from one that does not generalise (training loss low, held-out high) (issue 57; docs/evaluation.md, "Loss by
split and row kind").

The loss is the validation loss of the ``TrajectoryTransformerModule`` (``validation_losses``: masked MSE of the
actions and of the next states, plus the value output's where the model has one, over the rows of
``VALUE_SOURCES``), the module built from the model's weights and its recipe's ``optim`` section (the value loss's
tail weighting; the defaults where the bundle has no recipe). Rows come in one deterministic pass per split
(``TrajectoryDataModule.eval_dataloader``): the open-loop datasets of ``data.paths`` (their rows of
``data.sources``) and the DAgger folders of ``data.dagger_dirs`` (``<run>/dagger/iter-<i>``; their ``train`` and
``val`` splits), normalised with the model's statistics, at most ``rows`` rows each. Each term is averaged over its
own valid steps across the batches (a batch's mean weighted by its valid steps), so the numbers do not depend on
the batch size; with ``optim.value_tail_steps`` the value term's batches are weighted by their valid steps, not by
their tail weights. The same terms by steps to go (the buckets of ``ttompc.evaluation.value_error``) say where a
loss lives: on closed-loop rows the last steps of the expert's plans can dominate it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ttompc.data.config import DataConfig
from ttompc.errors import UserError
from ttompc.ranges import Checked, setting

if TYPE_CHECKING:
    from collections.abc import Iterable

    from torch import Tensor

    from ttompc.policy import Planner
    from ttompc.training.module import TrajectoryTransformerModule

KINDS = {"open_loop": False, "dagger": True}  # row kind -> TrajectoryDataModule.eval_dataloader(closed_loop=...)
TERMS = ("loss", "loss_action", "loss_state", "loss_value")


@dataclass
class LossConfig(Checked):
    """``ttompc evaluate loss`` settings (``key=value``): the model, the datasets (``data.paths``: open-loop
    folders, at least one; ``data.dagger_dirs``: DAgger folders), the splits and at most ``rows`` rows per split and
    row kind; ``out`` defaults to ``outputs/evaluate/loss-<model>`` (the model's zoo or folder name)."""

    model: str | None = None
    data: DataConfig = field(default_factory=lambda: DataConfig(verify_checksums=False))
    splits: list[str] = setting(factory=lambda: ["train", "val", "test"], nonempty=True, unique=True)
    rows: int = setting(2000, ge=1)
    device: str = setting("cpu", device="torch")
    out: str = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        bad = [s for s in self.splits if s not in ("train", "val", "test")]
        if bad:
            raise ValueError(f"splits must be among [train, val, test], got {self.splits}")

    def out_dir(self) -> Path:
        """``out``, else ``outputs/evaluate/loss-<model>`` (the model's zoo or folder name)."""
        return Path(self.out or f"outputs/evaluate/loss-{Path(str(self.model)).stem}")


def loss_module(planner: Planner) -> TrajectoryTransformerModule:
    """The LightningModule of ``planner``'s weights and statistics under its recipe's ``optim`` (module doc), in
    evaluation mode."""
    from ttompc.config import ConfigError, from_container, to_container
    from ttompc.training.config import OptimConfig
    from ttompc.training.module import TrajectoryTransformerModule

    try:
        optim = from_container(OptimConfig, planner.recipe.get("optim") or {})
    except ConfigError:  # a recipe of an older code version: the loss terms do not depend on the optimiser
        optim = OptimConfig()
    module = TrajectoryTransformerModule(
        model_config=to_container(planner.model.cfg),
        optim=to_container(optim),
        scenario=planner.scenario.name,
        scenario_version=planner.scenario.version,
        norm_stats=planner.stats.to_dict(),
        plot_trajectories=False,
    )
    module.model.load_state_dict(planner.model.state_dict())
    return module.to(planner.device).eval()


def _weights(batch: dict[str, Tensor]) -> dict[str, float]:
    """The valid steps each term of ``validation_losses`` averages over in ``batch``."""
    import torch

    from ttompc.training.module import VALUE_SOURCES

    mask = batch.get("mask", torch.ones_like(batch["timesteps"], dtype=torch.float32))
    value_rows = torch.isin(batch["source"], torch.as_tensor(VALUE_SOURCES)).to(mask.dtype)
    return {
        "loss_action": float(mask.sum()),
        "loss_state": float(batch.get("state_mask", mask).sum()),
        "loss_value": float((mask * value_rows[:, None]).sum()),
    }


class _TermMeans:
    """Each loss term's mean over valid steps, from batch means weighted by their valid steps (``_weights``)."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = {}
        self.steps: dict[str, float] = {}

    def add(self, out: dict[str, Tensor], weights: dict[str, float]) -> None:
        for k, v in out.items():
            if k != "loss" and weights[k] > 0:
                self.sums[k] = self.sums.get(k, 0.0) + float(v) * weights[k]
                self.steps[k] = self.steps.get(k, 0.0) + weights[k]

    def result(self) -> dict[str, float]:
        """The terms (nan for one not computed or without a valid step), ``loss``, the sum of the others, and
        ``steps``, the valid steps of the action term."""
        out = {k: self.sums[k] / self.steps[k] if k in self.steps else float("nan") for k in TERMS[1:]}
        loss = sum(self.sums[k] / self.steps[k] for k in self.steps) if self.steps else float("nan")
        return {"loss": loss, **out, "steps": self.steps.get("loss_action", 0.0)}


def _within(batch: dict[str, Tensor], keep: Tensor) -> dict[str, Tensor]:
    """``batch`` with only the steps where ``keep`` (B, L) valid (its masks restricted)."""
    import torch

    out = dict(batch)
    out["mask"] = batch.get("mask", torch.ones_like(keep, dtype=torch.float32)) * keep
    if "state_mask" in batch:
        out["state_mask"] = batch["state_mask"] * keep
    return out


def row_losses(
    module: TrajectoryTransformerModule, batches: Iterable[dict[str, Tensor]], rows: int, n_steps: int
) -> dict[str, Any]:
    """The loss terms of ``module`` over at most ``rows`` rows of ``batches``, each averaged over its valid steps
    (module doc): ``rows`` evaluated, the terms (nan for one the module does not compute or with no valid step, e.g.
    the value on REL rows, which the training loss leaves out too), ``loss``, the sum of the others, and
    ``buckets``: the same over the steps of each bucket of steps to go N − t (``BUCKETS`` of
    ``ttompc.evaluation.value_error``; N = ``n_steps``) that has one."""
    import torch

    from ttompc.evaluation.value_error import BUCKETS

    total = _TermMeans()
    buckets = {f"{lo}-{hi}": _TermMeans() for lo, hi in BUCKETS}
    seen = 0
    with torch.inference_mode():
        for b in batches:
            if seen >= rows:
                break
            if seen + len(b["source"]) > rows:
                b = {k: v[: rows - seen] for k, v in b.items()}
            seen += len(b["source"])
            total.add(module.validation_losses({k: v.to(module.device) for k, v in b.items()}), _weights(b))
            to_go = n_steps - b["timesteps"]
            for (lo, hi), means in zip(BUCKETS, buckets.values(), strict=True):
                part = _within(b, (to_go >= lo) & (to_go <= hi))
                if part["mask"].any():
                    means.add(
                        module.validation_losses({k: v.to(module.device) for k, v in part.items()}), _weights(part)
                    )
    by_bucket = {label: m.result() for label, m in buckets.items() if m.steps}
    return {"rows": seen, **total.result(), "buckets": by_bucket}


def fit_losses(cfg: LossConfig) -> list[dict[str, Any]]:
    """One row per (row kind, split) of ``cfg``: ``kind`` ("open_loop", "dagger"), ``split`` and ``row_losses``
    (``rows`` 0 and nan terms where the datasets have no such rows; DAgger rows only with ``data.dagger_dirs``)."""
    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.data.shards import ShardError
    from ttompc.parallel import single_torch_thread
    from ttompc.policy import Planner

    if not cfg.model:
        raise UserError("evaluate loss needs a model", "pass --model NAME (zoo name, hf://ORG/NAME, folder or .ckpt)")
    if not cfg.data.paths:
        raise UserError("evaluate loss needs an open-loop dataset", "pass data.paths=[FOLDER] (the model's data)")
    planner = Planner.from_pretrained(cfg.model, device=cfg.device)
    dm = TrajectoryDataModule(cfg.data)
    dm.setup("validate")
    if dm.scenario_name != planner.scenario.name:
        raise UserError(
            f"{cfg.model} is a {planner.scenario.name} model but {cfg.data.paths[0]} holds "
            f"{dm.scenario_name} trajectories",
            "pass the model's datasets",
        )
    dm.use_stats(planner.stats)
    module = loss_module(planner)
    out = []
    with single_torch_thread():
        for kind, closed in KINDS.items():
            if closed and not cfg.data.dagger_dirs:
                continue
            for split in cfg.splits:
                try:
                    loader = dm.eval_dataloader(split, closed_loop=closed)
                except ShardError:
                    out.append(
                        {
                            "kind": kind,
                            "split": split,
                            "rows": 0,
                            **dict.fromkeys(TERMS, float("nan")),
                            "steps": 0.0,
                            "buckets": {},
                        }
                    )
                    continue
                assert dm.n_steps is not None  # set by setup
                out.append({"kind": kind, "split": split, **row_losses(module, loader, cfg.rows, dm.n_steps)})
    return out


def format_losses(rows: list[dict[str, Any]], model: str) -> str:
    """The markdown table of ``fit_losses``' rows."""
    lines = [
        f"Training objective of {model} (masked MSE, normalised units) by row kind and split: both high is "
        "under-fitting, train low and held-out high is not generalising.",
        "",
        "| rows | split | rows evaluated | loss | action | next state | value |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        terms = " | ".join(_number(r[k]) for k in TERMS)
        lines.append(f"| {r['kind'].replace('_', '-')} | {r['split']} | {r['rows']} | {terms} |")
    labels = list(dict.fromkeys(label for r in rows for label in r["buckets"]))[::-1]  # the longest first
    lines += [
        "",
        "The loss by steps to go:",
        "",
        "| rows | split | " + " | ".join(labels) + " |",
        "|---|---|" + "---|" * len(labels),
    ]
    for r in rows:
        cells = " | ".join(_number(r["buckets"][b]["loss"]) if b in r["buckets"] else "–" for b in labels)
        lines.append(f"| {r['kind'].replace('_', '-')} | {r['split']} | {cells} |")
    return "\n".join(lines) + "\n"


def _number(x: float) -> str:
    return "–" if math.isnan(x) else f"{x:.4g}"


def run_fit_loss(cfg: LossConfig) -> dict[str, Any]:
    """Run ``fit_losses`` and write ``loss.json`` (config and rows) and ``loss.md`` (the table) into ``cfg.out_dir()``,
    a folder claimed before the model and the data are read (``report_files.claim_report``: new, empty or a loss
    report's, else a one-line ``UserError``)."""
    from ttompc.evaluation.metrics import write_json
    from ttompc.evaluation.report_files import claim_report

    out = claim_report(cfg.out_dir(), "loss")
    rows = fit_losses(cfg)
    table = format_losses(rows, str(cfg.model))
    write_json(out / "loss.json", {"config": asdict(cfg), "rows": rows})
    (out / "loss.md").write_text(table)
    return {"rows": rows, "table": table, "out": str(out)}
