"""``TrajectoryTransformerModule``: teacher-forced training of ``TrajectoryGPT`` (paper §IV-B, the loss of Eq. (7)).

Batch contract (from ``ttompc.data.datamodule.TrajectoryDataModule``; float32, already normalised)::

    states (B, L, n)   actions (B, L, m)   goals (B, L, n)   rtg (B, L, 1)   ctg (B, L, 1)   timesteps (B, L) int64
    target_actions (B, L, m)   target_next_states (B, L, n)   mask (B, L) float, 1 = valid step
    state_mask (B, L) float, optional: validity of target_next_states (default: mask)

loss = masked MSE(â, target_actions) + masked MSE(ŝ, target_next_states), equal weights like the reference; a model
with a value output adds masked MSE(V̂, rtg), equally weighted, over the steps of rows whose rtg is an optimum's
cost-to-go (``VALUE_SOURCES``: SCP and DAgger rows, which need ``source`` (B,) in the batch). With
``optim.trainable: value`` the policy's parameters are frozen and the loss is the value term alone.
Hyper-parameters are primitives only (dicts of numbers/strings), so the checkpoint loads with ``weights_only=True``
and is enough to build a ``Planner`` (``Planner.from_pretrained``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig
from torch import Tensor
from torch.optim import Optimizer

from ttompc.config import from_container
from ttompc.data.schema import SOURCE_CODES
from ttompc.policy.config import ModelConfig
from ttompc.policy.gpt import TrajectoryGPT
from ttompc.policy.stats import NormStats
from ttompc.policy.value import GaussNewtonValue
from ttompc.training.config import OptimConfig
from ttompc.training.loggers import log_figure, trajectory_figure

if TYPE_CHECKING:
    from ttompc.scenarios.base import Scenario

# rows whose rtg_t is the cost-to-go of an optimal (or expert) plan from s_t: the value output's targets. REL rows
# solve the relaxation, whose cost-to-go is lower than any feasible plan's.
VALUE_SOURCES = (SOURCE_CODES["scp"], SOURCE_CODES["dagger"])


def masked_mse(pred: Tensor, target: Tensor, mask: Tensor | None, delta: float | None = None) -> Tensor:
    """Mean squared error over valid steps (mask (B, L)) and all feature dims; with ``delta`` each element's error
    is squared up to ``delta`` and grows linearly beyond (2·delta·|e| − delta², a Huber loss scaled to match MSE
    inside delta)."""
    e = pred - target
    sq = e**2 if delta is None else torch.where(e.abs() <= delta, e**2, 2 * delta * e.abs() - delta**2)  # (B, L, k)
    if mask is None:
        return sq.mean()
    w = mask.to(sq.dtype).unsqueeze(-1)
    return (sq * w).sum() / (w.sum() * sq.shape[-1]).clamp_min(1.0)


class TrajectoryTransformerModule(L.LightningModule):
    def __init__(
        self,
        model_config: dict[str, Any],
        optim: dict[str, Any],
        scenario: str,
        scenario_version: str,
        norm_stats: dict[str, Any],
        recipe: dict[str, Any] | None = None,
        code_version: str | None = None,
        plot_trajectories: bool = True,
        scenario_spec: str | None = None,
        solver: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.model = TrajectoryGPT(from_container(ModelConfig, model_config))
        self.optim_cfg = from_container(OptimConfig, optim)
        self.stats = NormStats.from_dict(norm_stats)
        if isinstance(self.model.value_head, GaussNewtonValue):  # J = σ·½‖r‖² ≥ 0 (ttompc.policy.value)
            mu, sd = self.stats.mean_std("rtg", np.zeros(1))
            self.model.value_head.set_floor(float(mu[0]), float(sd[0]))
        if self.optim_cfg.trainable == "value":
            if self.model.value_head is None:
                raise ValueError("optim.trainable=value needs a value output (model.value_width > 0)")
            for name, p in self.model.named_parameters():
                p.requires_grad_(name.startswith("value_head."))
        self._plot_batch: dict[str, Tensor] | None = None

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        return self.model(
            batch["goals"], batch["rtg"], batch["ctg"], batch["states"], batch["actions"], batch["timesteps"]
        )

    def value_loss(self, batch: dict[str, Tensor]) -> Tensor:
        """Masked MSE of the value output against the normalised rtg, over the valid steps of ``VALUE_SOURCES``
        rows (0 when the batch has none); steps within ``optim.value_tail_steps`` of the end weigh
        ``optim.value_tail_weight``. With ``optim.value_grad_weight`` > 0 it adds that times the masked MSE of the
        value's gradient in the state against the rows' costates (``value_grad``, where ``grad_mask``): a Sobolev
        loss (in training; validation, under inference mode, reports the value term)."""
        states, known = batch["states"], batch.get("grad_mask")
        sobolev = self.optim_cfg.value_grad_weight > 0 and known is not None and bool(known.any())
        sobolev = sobolev and not torch.is_inference_mode_enabled()
        if sobolev:
            states = states.detach().requires_grad_(True)
        with torch.enable_grad():
            v = self.model.value(batch["goals"], states, batch["timesteps"])  # (B, L, 1)
            # v_t reads s_t alone: the gradient of the sum is each step's own (B, L, n)
            grad = torch.autograd.grad(v.sum(), states, create_graph=True)[0] if sobolev else None
        rows = torch.isin(batch["source"], torch.as_tensor(VALUE_SOURCES, device=v.device))  # (B,)
        mask = batch.get("mask", torch.ones_like(batch["timesteps"], dtype=v.dtype))
        mask = mask * rows[:, None].to(mask.dtype)  # (B, L)
        cfg = self.optim_cfg
        if cfg.value_tail_steps > 0:
            tail = (self.model.cfg.max_steps - batch["timesteps"]) <= cfg.value_tail_steps  # (B, L)
            mask = mask * torch.where(tail, cfg.value_tail_weight, 1.0).to(mask.dtype)
        loss = masked_mse(v, batch["rtg"], mask)
        if grad is not None:
            assert known is not None
            loss = loss + cfg.value_grad_weight * masked_mse(grad, batch["value_grad"], mask * known)
        return loss

    def _losses(self, batch: dict[str, Tensor], delta: float | None = None) -> dict[str, Tensor]:
        """The training loss ("loss") and its terms; "pred" holds the teacher-forced next states (not with
        ``optim.trainable: value``, which does not run the transformer)."""
        out: dict[str, Tensor] = {}
        if self.optim_cfg.trainable == "all":
            a_pred, s_pred = self(batch)
            mask = batch.get("mask")
            out["loss_action"] = masked_mse(a_pred, batch["target_actions"], mask, delta)
            out["loss_state"] = masked_mse(s_pred, batch["target_next_states"], batch.get("state_mask", mask), delta)
            out["loss"] = out["loss_action"] + out["loss_state"]
            out["pred"] = s_pred
        if self.model.value_head is not None:
            out["loss_value"] = self.value_loss(batch)
            out["loss"] = out.get("loss", 0.0) + out["loss_value"]
        return out

    def validation_losses(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """The loss ("loss") and its terms ("loss_action", "loss_state", "loss_value") of ``batch`` as validation
        logs them (plain MSE): what ``ttompc evaluate loss`` reports on any split."""
        return {k: v for k, v in self._losses(batch).items() if k.startswith("loss")}

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        out = self._losses(batch, self.optim_cfg.huber_delta)  # validation stays plain MSE
        B = batch["states"].shape[0]
        self.log("train/loss", out["loss"], prog_bar=True, batch_size=B)
        self.log_dict({f"train/{k}": v for k, v in out.items() if k.startswith("loss_")}, batch_size=B)
        return out["loss"]

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        out = self._losses(batch)
        B = batch["states"].shape[0]
        self.log("val/loss", out["loss"], prog_bar=True, sync_dist=True, batch_size=B)
        self.log_dict({f"val/{k}": v for k, v in out.items() if k.startswith("loss_")}, sync_dist=True, batch_size=B)
        if batch_idx == 0 and self.hparams["plot_trajectories"] and "pred" in out:
            s_pred = out["pred"]
            k = min(4, B)
            self._plot_batch = {
                "states": batch["states"][:k].detach().cpu(),
                "target": batch["target_next_states"][:k].detach().cpu(),
                "pred": s_pred[:k].detach().float().cpu(),
                "mask": batch.get("mask", torch.ones_like(batch["timesteps"], dtype=torch.float32))[:k].cpu(),
            }

    def on_validation_epoch_end(self) -> None:
        """A figure of teacher-forced next-state predictions vs targets (first validation batch, rank 0)."""
        if self._plot_batch is None or self.trainer.sanity_checking or not self.trainer.is_global_zero:
            return
        b, self._plot_batch = self._plot_batch, None
        denorm = lambda x: self.stats.denormalize("states", x.double()).numpy()  # noqa: E731
        fig = trajectory_figure(
            denorm(b["target"]), denorm(b["pred"]), b["mask"].numpy(), title=f"step {self.global_step}"
        )
        log_figure(self.trainer, "val/trajectories", fig, self.global_step)

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
        """AdamW (weight decay on the matrices only) with warm-up and the ``optim.schedule``, stepped per optimiser
        step. Fused (one kernel per step) on CUDA unless a GradScaler scales the gradients (16-mixed): Lightning
        unscales them before ``configure_gradient_clipping`` only for an optimiser that does not unscale inside its
        step. On the CPU, where it would be negligible, torch's default (docs/design.md)."""
        cfg = self.optim_cfg
        decay = [p for p in self.parameters() if p.requires_grad and p.dim() >= 2]
        no_decay = [p for p in self.parameters() if p.requires_grad and p.dim() < 2]
        # Lightning moved the model before this call; the Trainer is consulted on CUDA only
        fused = self.device.type == "cuda" and getattr(self.trainer.precision_plugin, "scaler", None) is None
        opt = torch.optim.AdamW(
            [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}],
            lr=cfg.lr,
            betas=(cfg.betas[0], cfg.betas[1]),
            fused=True if fused else None,
        )
        total = max(int(self.trainer.estimated_stepping_batches), 1) if cfg.schedule == "cosine" else 0

        def factor(step: int) -> float:
            if step < cfg.warmup_steps:
                return (step + 1) / cfg.warmup_steps
            if cfg.schedule == "constant":
                return 1.0
            progress = min((step - cfg.warmup_steps) / max(total - cfg.warmup_steps, 1), 1.0)
            return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))

        sched = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def configure_gradient_clipping(
        self,
        optimizer: Optimizer,
        gradient_clip_val: float | None = None,
        gradient_clip_algorithm: str | None = None,
    ) -> None:
        """Clip the global 2-norm of the gradients of ``optimizer``'s parameters to ``optim.grad_clip`` (0: off), as
        ``Trainer(gradient_clip_val=grad_clip)`` would, bit for bit. Done here because Lightning's AMP plugin refuses
        to clip for an optimiser that unscales inside its step (the fused AdamW of CUDA runs), even in bf16-mixed,
        which has no GradScaler. Lightning calls this after backward and, under a GradScaler (whose optimiser is not
        fused: ``configure_optimizers``), after unscaling. The recipe owns clipping: a Trainer's
        ``gradient_clip_val`` is refused (ValueError)."""
        if gradient_clip_val is not None:
            raise ValueError(
                f"Trainer(gradient_clip_val={gradient_clip_val}): clipping is optim.grad_clip, applied by the module"
            )
        if self.optim_cfg.grad_clip > 0:
            params = [p for group in optimizer.param_groups for p in group["params"]]
            torch.nn.utils.clip_grad_norm_(params, self.optim_cfg.grad_clip)


class SaveLastCheckpoint(L.Callback):
    """Keep ``last.ckpt`` current: every ``every_n_steps`` optimiser steps and when fitting ends (in the training
    processes, so also under spawn-based strategies). Resuming therefore never loses more than that many steps."""

    def __init__(self, path: Path, every_n_steps: int) -> None:
        self.path, self.every_n_steps = path, every_n_steps
        self._saved_at = -1

    def _save(self, trainer: L.Trainer) -> None:
        if trainer.global_step != self._saved_at:
            trainer.save_checkpoint(self.path, weights_only=False)  # full state; saying so silences a log line
            self._saved_at = trainer.global_step

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if self.every_n_steps > 0 and trainer.global_step % self.every_n_steps == 0:
            self._save(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._save(trainer)


def build_module(
    model: ModelConfig,
    optim: OptimConfig,
    scenario: Scenario,
    stats: NormStats,
    *,
    recipe: Any,
    plot_trajectories: bool,
    backend: str = "auto",
) -> TrajectoryTransformerModule:
    """The LightningModule of ``model`` on ``scenario``'s data, built the same way by pre-training and DAgger: typed
    configs in, primitives stored as hyper-parameters (so the checkpoint loads with ``weights_only=True`` and is
    enough for ``Planner.from_pretrained``), with the recipe (a typed config), the code version and the solver path
    of the run's ``backend`` on ``scenario`` (``solver_path``: name, chain, trust-region norm) recorded."""
    from ttompc.config import to_container
    from ttompc.scenarios import scenario_spec as spec_of
    from ttompc.solvers.backends import solver_path
    from ttompc.version import code_version

    return TrajectoryTransformerModule(
        model_config=to_container(model),
        optim=to_container(optim),
        scenario=scenario.name,
        scenario_version=scenario.version,
        scenario_spec=spec_of(scenario),  # how a fresh process loads it
        norm_stats=stats.to_dict(),
        recipe=to_container(recipe),
        code_version=code_version(),
        plot_trajectories=plot_trajectories,
        solver=solver_path(backend, scenario),
    )
