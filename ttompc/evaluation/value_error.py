"""How well a model's value output knows the cost-to-go, by steps to go: on held-out rows of an open-loop dataset
whose rtg is an optimum's cost-to-go (SCP rows), the error of J = −rtg predicted from (goal, s_t, t).

    python -m ttompc.evaluation.value_error --model NAME [NAME ...] --data DATA [--split test --rows 500]

prints one JSON line per model: per bucket of steps to go, the rows' mean |J*|, the mean absolute error and its
ratio to the mean |J*| (the value's relative error where it matters to a window's terminal cost: its last steps),
and where the rows carry costates the gradient's relative error Σ‖∇V − λ‖ / Σ‖λ‖ (normalised units).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from typing import Any

import numpy as np

BUCKETS = ((1, 5), (6, 10), (11, 20), (21, 50), (51, 100))  # steps to go, inclusive


def value_errors(model: str, data: Sequence[str], split: str = "test", rows: int = 500) -> dict[str, Any]:
    """The value output's errors of ``model`` on at most ``rows`` SCP rows of the ``split`` of ``data``."""
    import torch

    from ttompc.data.config import DataConfig
    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.data.schema import SOURCE_CODES
    from ttompc.policy import Planner

    planner = Planner.from_pretrained(model)
    if not planner.has_value:
        raise ValueError(f"{model} has no value output")
    dm = TrajectoryDataModule(DataConfig(paths=list(data), sources="scp", batch_size=50, verify_checksums=False))
    dm.setup("test")
    dm.use_stats(planner.stats)
    loader = dm.test_dataloader() if split == "test" else dm.val_dataloader()
    st, N = planner.stats, planner.model.cfg.max_steps
    err: list[np.ndarray] = []
    true: list[np.ndarray] = []
    togo: list[np.ndarray] = []
    gerr: list[np.ndarray] = []  # per step: (‖∇V − λ‖, ‖λ‖, steps to go) where the row has costates
    seen = 0
    for b in loader:
        keep = (b["source"] == SOURCE_CODES["scp"]) & (seen + torch.arange(len(b["source"])) < rows)
        if not keep.any():
            break
        states = b["states"].clone().requires_grad_(True)
        v = planner.model.value(b["goals"], states, b["timesteps"])
        grad = torch.autograd.grad(v.sum(), states)[0]  # (B, L, n), normalised units
        known = (b["grad_mask"] > 0) & keep[:, None]
        if known.any():
            g, t = b["value_grad"][known], (N - b["timesteps"])[known]
            gerr.append(np.stack([(grad[known] - g).norm(dim=-1).numpy(), g.norm(dim=-1).numpy(), t.numpy()], 1))
        with torch.no_grad():
            J_hat = -st.denormalize("rtg", v.detach().double())[..., 0].numpy()  # (B, L)
        J = -st.denormalize("rtg", b["rtg"].double())[..., 0].numpy()
        valid = (b.get("mask", torch.ones_like(b["timesteps"], dtype=torch.float32)) > 0).numpy()
        valid &= keep.numpy()[:, None]
        err.append(np.abs(J_hat - J)[valid])
        true.append(np.abs(J)[valid])
        togo.append((N - b["timesteps"].numpy())[valid])
        seen += int(keep.sum())
    e, j, g = np.concatenate(err), np.concatenate(true), np.concatenate(togo)
    ge = np.concatenate(gerr) if gerr else np.zeros((0, 3))
    out: dict[str, Any] = {"model": model, "rows": seen, "buckets": {}}
    for lo, hi in BUCKETS:
        m = (g >= lo) & (g <= hi)
        if m.any():
            out["buckets"][f"{lo}-{hi}"] = {
                "mean_abs_J": float(j[m].mean()),
                "mae": float(e[m].mean()),
                "relative": float(e[m].mean() / j[m].mean()),
            }
        mg = (ge[:, 2] >= lo) & (ge[:, 2] <= hi)
        if mg.any():
            out["buckets"].setdefault(f"{lo}-{hi}", {})["gradient_relative"] = float(ge[mg, 0].sum() / ge[mg, 1].sum())
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ttompc.evaluation.value_error", description=__doc__.split("\n\n")[0])
    p.add_argument("--model", nargs="+", required=True, help="zoo names, bundle folders or checkpoints")
    p.add_argument("--data", nargs="+", required=True, help="open-loop dataset folders")
    p.add_argument("--split", default="test", choices=("test", "val"))
    p.add_argument("--rows", type=int, default=500)
    a = p.parse_args(argv)
    for model in a.model:
        print(json.dumps(value_errors(model, a.data, a.split, a.rows)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
