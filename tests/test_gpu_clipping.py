"""Gradient clipping with the fused AdamW that CUDA runs get, checked without a GPU: torch's CPU build has a fused
AdamW too (``_step_supports_amp_scaling``, the flag Lightning's AMP plugin looks at), so a CPU run with a fused
optimizer takes the same Lightning code path as a GPU run (``MixedPrecision`` refused to clip for it)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import lightning as L
import pytest
import torch
from test_training import ToyDataModule, tiny_config

from ttompc.config import to_container
from ttompc.training.module import TrajectoryTransformerModule
from ttompc.training.run import train


def global_grad_norm(optimizer: torch.optim.Optimizer) -> float:
    """The 2-norm of all gradients of ``optimizer``'s parameters together."""
    grads = [p.grad for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
    return torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads])).item()


def recording_adamw(monkeypatch: pytest.MonkeyPatch, fused: bool | None) -> tuple[list[bool], list[float]]:
    """Replace ``torch.optim.AdamW`` by one that is fused as ``fused`` says (None: as the module asks) and records,
    per optimiser step, the global gradient norm the update uses (after Lightning's closure, unscaling and
    clipping). Returns (fused flag of each optimizer built, norms)."""
    built: list[bool] = []
    norms: list[float] = []

    class RecordingAdamW(torch.optim.AdamW):
        def __init__(self, params: Any, **kwargs: Any) -> None:
            if fused is not None:
                kwargs["fused"] = fused
            super().__init__(params, **kwargs)
            built.append(bool(self.defaults["fused"]))

        def step(self, closure: Callable[[], Any] | None = None) -> Any:
            loss = closure() if closure is not None else None  # Lightning's: forward, backward, clipping
            norms.append(global_grad_norm(self))
            super().step()
            return loss

    monkeypatch.setattr(torch.optim, "AdamW", RecordingAdamW)
    return built, norms


class PreClipNorms(L.Callback):
    """The global gradient norm of each step before clipping (Lightning calls this hook after unscaling, before
    ``configure_gradient_clipping``)."""

    def __init__(self) -> None:
        self.norms: list[float] = []

    def on_before_optimizer_step(self, trainer: L.Trainer, pl_module: L.LightningModule, optimizer: Any) -> None:
        self.norms.append(global_grad_norm(optimizer))


@pytest.mark.parametrize(
    ("precision", "fused", "clip"),
    [("bf16-mixed", True, 0.05), ("32-true", True, 0.05), ("32-true", None, 0.0)],
    ids=["bf16-fused", "fp32-fused", "fp32-off"],
)
def test_clipping_runs_and_clips_with_the_fused_optimizer(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, precision: str, fused: bool | None, clip: float
) -> None:
    """The Trainer ``build_trainer`` makes trains with a fused AdamW and ``optim.grad_clip`` in bf16-mixed (the GPU
    recipes' setting; Lightning raised "does not allow for gradient clipping" at step one) and in 32-true: every
    update uses gradients of global norm min(norm, grad_clip); ``grad_clip: 0`` leaves them as they are."""
    built, post = recording_adamw(monkeypatch, fused)
    pre = PreClipNorms()
    torch.manual_seed(0)
    overrides = ("trainer.max_steps=3", f"trainer.precision={precision}", f"optim.grad_clip={clip}", "logger.kind=none")
    res = train(tiny_config(tmp_path / "run", *overrides), ToyDataModule(n=32), callbacks=[pre])
    assert res.global_step == 3 and built == [fused is True]
    assert len(pre.norms) == len(post) == 3
    if clip > 0:
        assert all(n > clip for n in pre.norms), pre.norms  # so clipping is exercised on every step
    assert post == pytest.approx([min(n, clip) if clip > 0 else n for n in pre.norms], rel=1e-4)


def toy_module(dm: ToyDataModule, *overrides: str) -> TrajectoryTransformerModule:
    """The tiny recipe's module on ``dm``'s (set-up) data, with a constant schedule (its optimiser is then built
    without a Trainer)."""
    assert dm.stats is not None
    cfg = tiny_config(Path("unused"), "optim.schedule=constant", *overrides)
    return TrajectoryTransformerModule(
        to_container(cfg.model), to_container(cfg.optim), "toy", "0.1", dm.stats.to_dict()
    )


def test_module_clipping_is_lightnings_norm_clipping() -> None:
    """The module clips exactly as ``Trainer(gradient_clip_val=grad_clip)`` did on the CPU (Lightning's
    ``Precision.clip_gradients``: ``clip_grad_norm_`` of the optimiser's parameters, global 2-norm), bit for bit;
    ``grad_clip: 0`` is off; a Trainer's ``gradient_clip_val`` is refused."""
    from lightning.pytorch.plugins.precision import Precision
    from lightning.pytorch.utilities import GradClipAlgorithmType

    dm = ToyDataModule(n=16, batch_size=16)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    for clip in (0.05, 0.0):
        torch.manual_seed(0)
        module = toy_module(dm, f"optim.grad_clip={clip}")
        opt = module.configure_optimizers()["optimizer"]
        module._losses(batch)["loss"].backward()
        raw = [p.grad.clone() for p in module.parameters() if p.grad is not None]
        module.configure_gradient_clipping(opt)
        ours = [p.grad.clone() for p in module.parameters() if p.grad is not None]
        for p, g in zip((p for p in module.parameters() if p.grad is not None), raw, strict=True):
            p.grad = g.clone()
        Precision().clip_gradients(opt, clip, GradClipAlgorithmType.NORM)
        theirs = [p.grad for p in module.parameters() if p.grad is not None]
        assert all(torch.equal(a, b) for a, b in zip(ours, theirs, strict=True)), clip
        assert any(not torch.equal(a, b) for a, b in zip(ours, raw, strict=True)) == (clip > 0)
    with pytest.raises(ValueError, match=r"optim\.grad_clip"):  # one place says how to clip: the recipe
        module.configure_gradient_clipping(opt, gradient_clip_val=1.0)


def fp16_scaler_plugin() -> Any:
    """Lightning's 16-mixed AMP with a GradScaler, on the CPU (``Trainer(precision="16-mixed")`` would be bf16
    there)."""
    from lightning.pytorch.plugins.precision import MixedPrecision

    return MixedPrecision("16-mixed", "cpu", scaler=torch.amp.GradScaler("cpu"))


def test_clipping_sees_unscaled_gradients_under_a_grad_scaler(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """16-mixed with a GradScaler (the unfused optimiser it gets): the module clips the unscaled gradients, so each
    update uses gradients of global norm min(norm, grad_clip), not a scaled norm clipped."""
    real_trainer = L.Trainer

    def fp16_trainer(**kwargs: Any) -> L.Trainer:
        kwargs.pop("precision")
        kwargs["plugins"] = [*kwargs["plugins"], fp16_scaler_plugin()]
        return real_trainer(**kwargs)

    monkeypatch.setattr(L, "Trainer", fp16_trainer)
    built, post = recording_adamw(monkeypatch, None)
    pre = PreClipNorms()
    torch.manual_seed(0)
    overrides = ("trainer.max_steps=3", "optim.grad_clip=0.05", "logger.kind=none")
    res = train(tiny_config(tmp_path / "run", *overrides), ToyDataModule(n=32), callbacks=[pre])
    assert res.global_step == 3 and built == [False] and len(pre.norms) == 3
    assert all(0.05 < n < 1e3 for n in pre.norms), pre.norms  # unscaled (the scale starts at 65536), then clipped
    assert post == pytest.approx([0.05] * 3, rel=1e-4)


def test_adamw_is_fused_on_cuda_unless_a_grad_scaler(monkeypatch: pytest.MonkeyPatch) -> None:
    """``configure_optimizers`` builds a fused AdamW when the module is on CUDA (faked: only the module's device is
    read) in bf16-mixed and 32-true, an unfused one under a GradScaler (16-mixed) and on the CPU."""
    dm = ToyDataModule(n=8)
    dm.setup("fit")
    module = toy_module(dm)

    def fused(device: str, **trainer_kwargs: Any) -> bool:
        monkeypatch.setattr(TrajectoryTransformerModule, "device", property(lambda self: torch.device(device)))
        module.trainer = L.Trainer(accelerator="cpu", logger=False, enable_checkpointing=False, **trainer_kwargs)
        return bool(module.configure_optimizers()["optimizer"].defaults["fused"])

    assert fused("cuda", precision="bf16-mixed") and fused("cuda", precision="32-true")
    assert not fused("cuda", plugins=[fp16_scaler_plugin()])
    assert not fused("cpu", precision="bf16-mixed")
