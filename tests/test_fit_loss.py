"""``ttompc evaluate loss``: the training objective by split, open-loop and DAgger rows apart, on a tiny generated
set: each term is the masked MSE over all valid steps (computed here independently of the module's loss code), does
not depend on the batch size, and the command writes its report."""

from __future__ import annotations

import json
from pathlib import Path

import data_fakes as fakes
import helpers
import numpy as np
import pytest
import torch

from ttompc.cli import main
from ttompc.data.config import DataConfig
from ttompc.data.datamodule import TrajectoryDataModule
from ttompc.data.schema import SOURCE_CODES, make_row, trajectory_features
from ttompc.data.shards import ShardWriter
from ttompc.policy import ModelConfig, Planner, TrajectoryGPT
from ttompc.scenarios import get_scenario
from ttompc.training.fit_loss import LossConfig, fit_losses

DAGGER_ROWS = 10
N = 12  # data-fake's steps


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """An open-loop set of 30 problems (REL and SCP rows), a DAgger folder (train and val, no test) and a model with
    a value output, saved as a bundle."""
    root = tmp_path_factory.mktemp("loss")
    ol = root / "ol"
    helpers.tiny_dataset(ol, "data-fake", 30, (0.6, 0.2, 0.2), shard_size=10, seed=1, solver=fakes.SOLVER)
    sc = get_scenario("data-fake")
    writer = ShardWriter(root / "dagger", trajectory_features(sc))
    rng = np.random.default_rng(0)
    rows = []
    for i in range(DAGGER_ROWS):
        p = sc.sample(rng)
        U = rng.normal(scale=0.05, size=(sc.n_steps, sc.control_dim))
        X = sc.rollout(p, U)
        rows.append(
            make_row(
                sc,
                p,
                problem_id=10_000 + i,
                seed=i,
                source="dagger",
                iteration=0,
                states=sc.to_model_states(p, X),
                actions=U,
                states_opt=X,
            )
        )
    writer.write(rows, 0)
    writer.write(rows[:3], 0, split="val")
    dm = TrajectoryDataModule(DataConfig(paths=[str(ol)]))
    dm.setup("validate")
    torch.manual_seed(0)
    cfg = ModelConfig(n_embd=16, n_layer=1, n_head=2, max_steps=sc.n_steps, dropout=0.0, value_width=8)
    assert dm.stats is not None
    bundle = Planner(TrajectoryGPT(cfg), sc, dm.stats).save(root / "bundle")
    return {"ol": ol, "dagger": root / "dagger", "bundle": bundle}


def _config(data: dict[str, Path], batch_size: int, **kw: object) -> LossConfig:
    dc = DataConfig(paths=[str(data["ol"])], dagger_dirs=[str(data["dagger"])], batch_size=batch_size)
    return LossConfig(model=str(data["bundle"]), data=dc, **kw)  # type: ignore[arg-type]


def _by_hand(
    data: dict[str, Path], closed_loop: bool, split: str, last: int | None = None
) -> tuple[int, float, float, float]:
    """Rows, action MSE, next-state MSE and value MSE (over VALUE_SOURCES rows) of the split over all valid steps
    (``last``: those with at most that many steps to go), from the model's forward pass."""
    planner = Planner.from_pretrained(data["bundle"])
    dm = TrajectoryDataModule(DataConfig(paths=[str(data["ol"])], dagger_dirs=[str(data["dagger"])], batch_size=7))
    dm.setup("validate")
    dm.use_stats(planner.stats)
    n = 0
    sq = {"a": 0.0, "s": 0.0, "v": 0.0}
    count = {"a": 0.0, "s": 0.0, "v": 0.0}
    with torch.no_grad():
        for b in dm.eval_dataloader(split, closed_loop=closed_loop):
            n += len(b["source"])
            a, s = planner.model(b["goals"], b["rtg"], b["ctg"], b["states"], b["actions"], b["timesteps"])
            v = planner.model.value(b["goals"], b["states"], b["timesteps"])
            keep = torch.ones_like(b["mask"]) if last is None else (N - b["timesteps"] <= last).float()
            mask = (b["mask"] * keep)[..., None]
            value_rows = (b["source"] == SOURCE_CODES["scp"]) | (b["source"] == SOURCE_CODES["dagger"])
            vmask = mask * value_rows[:, None, None]
            sq["a"] += float(((a - b["target_actions"]) ** 2 * mask).sum())
            count["a"] += float(mask.sum()) * a.shape[-1]
            state_mask = (b.get("state_mask", b["mask"]) * keep)[..., None]
            sq["s"] += float(((s - b["target_next_states"]) ** 2 * state_mask).sum())
            count["s"] += float(state_mask.sum()) * s.shape[-1]
            sq["v"] += float(((v - b["rtg"]) ** 2 * vmask).sum())
            count["v"] += float(vmask.sum())
    return n, sq["a"] / count["a"], sq["s"] / count["s"], sq["v"] / count["v"]


def test_losses_by_kind_and_split_are_the_masked_mse_over_all_steps(data: dict[str, Path]) -> None:
    rows = {(r["kind"], r["split"]): r for r in fit_losses(_config(data, batch_size=4))}
    assert list(rows) == [("open_loop", s) for s in ("train", "val", "test")] + [
        ("dagger", s) for s in ("train", "val", "test")
    ]
    assert rows[("dagger", "train")]["rows"] == DAGGER_ROWS and rows[("dagger", "val")]["rows"] == 3
    assert rows[("dagger", "test")]["rows"] == 0 and np.isnan(rows[("dagger", "test")]["loss"])
    for kind, split in [("open_loop", "train"), ("open_loop", "test"), ("dagger", "train")]:
        n, action, state, value = _by_hand(data, kind == "dagger", split)
        r = rows[(kind, split)]
        assert r["rows"] == n
        assert r["loss_action"] == pytest.approx(action, rel=1e-5)
        assert r["loss_state"] == pytest.approx(state, rel=1e-5)
        assert r["loss_value"] == pytest.approx(value, rel=1e-5)
        assert r["loss"] == pytest.approx(action + state + value, rel=1e-5)
        # by steps to go: the last five steps by hand, and the buckets' means recombine into the whole's
        _, action, state, value = _by_hand(data, kind == "dagger", split, last=5)
        last5 = r["buckets"]["1-5"]
        assert last5["loss_action"] == pytest.approx(action, rel=1e-5)
        assert last5["loss_state"] == pytest.approx(state, rel=1e-5)
        assert last5["loss_value"] == pytest.approx(value, rel=1e-5)
        steps = sum(b["steps"] for b in r["buckets"].values())
        assert steps == r["steps"] and list(r["buckets"]) == ["1-5", "6-10", "11-20"]  # N = 12 steps to go at most
        recombined = sum(b["loss_action"] * b["steps"] for b in r["buckets"].values()) / steps
        assert recombined == pytest.approx(r["loss_action"], rel=1e-5)
    # another batch size, the same numbers; ``rows`` caps every (kind, split)
    again = {(r["kind"], r["split"]): r for r in fit_losses(_config(data, batch_size=32))}
    for key, r in rows.items():
        for k in ("rows", "loss_action", "loss_state", "loss_value"):
            assert again[key][k] == pytest.approx(r[k], rel=1e-5, nan_ok=True), (key, k)
    capped = fit_losses(_config(data, batch_size=4, rows=5, splits=["train"]))
    assert [(r["kind"], r["rows"]) for r in capped] == [("open_loop", 5), ("dagger", 5)]


def test_evaluate_loss_command(tmp_path: Path, data: dict[str, Path]) -> None:
    out = tmp_path / "loss"
    rc = main(
        [
            "evaluate",
            "loss",
            "--model",
            str(data["bundle"]),
            f"data.paths=[{data['ol']}]",
            f"data.dagger_dirs=[{data['dagger']}]",
            "splits=[train,val]",
            f"--out={out}",
        ]
    )
    assert rc == 0
    report = json.loads((out / "loss.json").read_text())
    assert [(r["kind"], r["split"]) for r in report["rows"]] == [
        ("open_loop", "train"),
        ("open_loop", "val"),
        ("dagger", "train"),
        ("dagger", "val"),
    ]
    assert "| dagger | val | 3 |" in (out / "loss.md").read_text()
    assert main(["evaluate", "loss", f"data.paths=[{data['ol']}]", f"--out={out}"]) == 2  # no model
    assert main(["evaluate", "loss", "--model", str(data["bundle"]), f"--out={out}"]) == 2  # no data
    assert main(["evaluate", "loss", "--model", str(data["bundle"]), "splits=[dev]", f"--out={out}"]) == 2
