"""Streaming DataModule: batch contract, normalisation, windows, mixing ratio, rank/worker splitting, errors."""

from __future__ import annotations

import itertools
from pathlib import Path

import data_fakes as fakes
import helpers
import numpy as np
import pytest
import torch

from ttompc.data.config import DataConfig
from ttompc.data.datamodule import TrajectoryDataModule
from ttompc.data.schema import make_row, trajectory_features
from ttompc.data.shards import ShardError, ShardWriter, read_shard
from ttompc.scenarios import get_scenario

N, n, m = 12, 6, 3


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("dm")
    ol = root / "fake-ol"
    helpers.tiny_dataset(ol, "data-fake", 120, (0.7, 0.15, 0.15), shard_size=20, seed=1, solver=fakes.SOLVER)
    sc = get_scenario("data-fake")
    dirs = {}
    for it, count in ((0, 40), (1, 20)):  # two DAgger iterations written through the shared writer API
        writer = ShardWriter(root / f"dagger-{it}", trajectory_features(sc))
        rng = np.random.default_rng(it)
        rows = []
        for i in range(count):
            p = sc.sample(rng)
            U = rng.normal(scale=0.05, size=(N, m))
            X = sc.rollout(p, U)
            rows.append(
                make_row(
                    sc,
                    p,
                    problem_id=10_000 * (it + 1) + i,
                    seed=i,
                    source="dagger",
                    iteration=it,
                    states=sc.to_model_states(p, X),
                    actions=U,
                    states_opt=X,
                )
            )
        writer.write(rows[: count // 2], 0)
        writer.write(rows[count // 2 :], 1)
        writer.write(rows[:3], 0, split="val")
        dirs[f"dagger{it}"] = root / f"dagger-{it}"
    return {"ol": ol, **dirs}


def _dm(data: dict[str, Path], **kw) -> TrajectoryDataModule:
    cfg = DataConfig(paths=[str(data["ol"])], batch_size=32, shuffle_pool=128, context_length=N, seed=3)
    for k, v in kw.items():
        setattr(cfg, k, v)
    dm = TrajectoryDataModule(cfg)
    dm.setup("fit")
    return dm


def _stored(root: Path, split: str) -> dict[tuple[int, int], dict]:
    out = {}
    for f in sorted((root / split).glob("*.parquet")):
        for r in read_shard(f).with_format("numpy"):
            out[(int(r["problem_id"]), {"rel": 0, "scp": 1, "dagger": 2}[r["source"]])] = r
    return out


def test_batch_contract_windows_and_values(data: dict[str, Path]) -> None:
    dm = _dm(data, context_length=5)
    assert dm.scenario_name == "data-fake" and dm.n_steps == N
    batch = next(iter(dm.train_dataloader()))
    B, L = 32, 5
    shapes = {
        "states": (B, L, n),
        "actions": (B, L, m),
        "goals": (B, L, n),
        "rtg": (B, L, 1),
        "ctg": (B, L, 1),
        "timesteps": (B, L),
        "target_actions": (B, L, m),
        "target_next_states": (B, L, n),
        "mask": (B, L),
        "value_grad": (B, L, n),
        "grad_mask": (B, L),
        "source": (B,),
        "problem_id": (B,),
    }
    assert {k: tuple(v.shape) for k, v in batch.items()} == shapes
    assert not batch["grad_mask"].any() and not batch["value_grad"].any()  # rows without costates: no target
    for k, v in batch.items():
        assert v.dtype == (torch.int64 if k in ("timesteps", "source", "problem_id") else torch.float32), k
    t = batch["timesteps"].numpy()
    assert np.all(np.diff(t, axis=1) == 1) and t.min() >= 0 and t.max() <= N - 1
    assert len(np.unique(t[:, 0])) > 1, "windows should start at random steps"
    stored, st = _stored(data["ol"], "train"), dm.stats
    for b in range(B):
        r = stored[(int(batch["problem_id"][b]), int(batch["source"][b]))]
        tb = t[b]
        for key, col, stat in (
            ("states", "states", "states"),
            ("actions", "actions", "actions"),
            ("target_next_states", "target_next_states", "states"),
        ):
            np.testing.assert_allclose(st.denormalize(stat, batch[key][b].numpy()), r[col][tb], rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(st.denormalize("rtg", batch["rtg"][b].numpy())[:, 0], r["rtg"][tb], atol=1e-4)
        np.testing.assert_allclose(
            st.denormalize("goals", batch["goals"][b].numpy()), np.tile(r["goal"], (L, 1)), rtol=1e-4, atol=1e-5
        )
    assert torch.all(batch["mask"] == 1)


def test_default_context_is_the_datasets_horizon(data: dict[str, Path]) -> None:
    """DataConfig.context_length None (the default) means the whole horizon N of the datasets' scenario."""
    dm = _dm(data, context_length=None)
    batch = next(iter(dm.val_dataloader()))
    assert batch["timesteps"].shape[1] == N and torch.all(batch["timesteps"][:, 0] == 0)
    with pytest.raises(ValueError, match=rf"\[1, {N}\]"):
        _dm(data, context_length=N + 1)


def test_train_batches_are_normalised(data: dict[str, Path]) -> None:
    dm = _dm(data, train_batches_per_epoch=60)
    batches = list(dm.train_dataloader())
    assert len(batches) == 60
    for key in ("states", "actions", "goals", "rtg"):
        x = torch.cat([b[key].reshape(-1, b[key].shape[-1]) for b in batches])
        assert torch.all(x.mean(0).abs() < 0.1), (key, x.mean(0))
        constant = torch.as_tensor(dm.stats.std[key] == 0)  # e.g. zero goal velocities normalise to 0
        assert torch.all(torch.where(constant, x.std(0), (x.std(0) - 1).abs()) < 0.1), (key, x.std(0))


def test_epochs_reshuffle_and_sources_filter(data: dict[str, Path]) -> None:
    dm = _dm(data, train_batches_per_epoch=3, sources="scp")
    loader = dm.train_dataloader()
    first = [b["problem_id"].tolist() for b in loader]
    second = [b["problem_id"].tolist() for b in loader]
    assert first != second
    assert all(torch.all(b["source"] == 1) for b in itertools.chain(loader, dm.val_dataloader()))


@pytest.mark.parametrize("p", [0.9, 0.6])
def test_mixing_ratio_holds_statistically(data: dict[str, Path], p: float) -> None:
    dm = _dm(data, dagger_dirs=[str(data["dagger0"])], open_loop_fraction=p, train_batches_per_epoch=40)
    sources = torch.cat([b["source"] for b in dm.train_dataloader()]).numpy()
    k = len(sources)
    share = float(np.mean(sources != 2))
    assert abs(share - p) < 3 * np.sqrt(p * (1 - p) / k), share
    assert set(np.unique(sources)) == {0, 1, 2}


def test_growing_closed_loop_share(data: dict[str, Path]) -> None:
    dirs = [str(data["dagger0"]), str(data["dagger1"])]
    dm = _dm(data, dagger_dirs=dirs[:1], closed_loop_share="grow", open_loop_fraction=0.9)
    assert dm.open_loop_fraction() == pytest.approx(0.9)  # 9:1 at the first iteration
    dm = _dm(data, dagger_dirs=dirs, closed_loop_share="grow", open_loop_fraction=0.9)
    assert dm.open_loop_fraction() == pytest.approx(9 * 20 / (9 * 20 + 60))  # then the CL share grows
    assert len(list(dm.dagger_val_dataloader())) == 1


def test_two_ranks_and_workers_split_eval_disjointly_and_completely(
    data: dict[str, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    expected = set(_stored(data["ol"], "val"))
    for num_workers in (0, 2):
        seen: list[tuple[int, int]] = []
        for rank in (0, 1):
            monkeypatch.setenv("RANK", str(rank))
            monkeypatch.setenv("WORLD_SIZE", "2")
            dm = _dm(data, num_workers=num_workers, eval_batch_size=7)
            seen += [
                (int(p), int(s)) for b in dm.val_dataloader() for p, s in zip(b["problem_id"], b["source"], strict=True)
            ]
        assert len(seen) == len(set(seen)) and set(seen) == expected, num_workers


def test_val_is_deterministic(data: dict[str, Path]) -> None:
    dm = _dm(data, context_length=4)
    a, b = list(dm.val_dataloader()), list(dm.val_dataloader())
    assert all(torch.equal(x[k], y[k]) for x, y in zip(a, b, strict=True) for k in x)
    assert len(list(dm.test_dataloader())) > 0


def test_two_ranks_train_on_disjoint_problems(data: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    ids = []
    for rank in (0, 1):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        dm = _dm(data, train_batches_per_epoch=4)
        ids.append({int(p) for b in dm.train_dataloader() for p in b["problem_id"]})
    assert ids[0] and ids[1] and not ids[0] & ids[1]


def test_corrupt_shard_is_reported_with_its_path(data: dict[str, Path], tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(data["ol"], copy)
    victim = sorted((copy / "train").glob("*.parquet"))[1]
    victim.write_bytes(victim.read_bytes()[:200])
    with pytest.raises(ShardError, match=str(victim)):
        _dm({"ol": copy})
    dm = _dm({"ol": copy}, verify_checksums=False, train_batches_per_epoch=50)
    with pytest.raises(ShardError, match=str(victim)):
        list(dm.train_dataloader())


def test_lightning_fit_streams_new_batches_each_epoch(data: dict[str, Path], tmp_path: Path) -> None:
    import lightning as L

    class Probe(L.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.layer = torch.nn.Linear(n, m)
            self.seen: list[tuple[int, list[int]]] = []
            self.val_rows = 0

        def training_step(self, batch: dict, idx: int) -> torch.Tensor:
            self.seen.append((self.current_epoch, batch["problem_id"].tolist()))
            return torch.nn.functional.mse_loss(self.layer(batch["states"]), batch["target_actions"])

        def validation_step(self, batch: dict, idx: int) -> None:
            self.val_rows += len(batch["problem_id"])

        def configure_optimizers(self) -> torch.optim.Optimizer:
            return torch.optim.SGD(self.parameters(), lr=0.01)

    dm = TrajectoryDataModule(
        DataConfig(paths=[str(data["ol"])], batch_size=8, shuffle_pool=32, context_length=N, train_batches_per_epoch=3)
    )
    probe = Probe()
    trainer = L.Trainer(
        max_epochs=2,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=tmp_path,
        num_sanity_val_steps=0,
    )
    trainer.fit(probe, datamodule=dm)
    assert [e for e, _ in probe.seen] == [0, 0, 0, 1, 1, 1]
    assert [ids for e, ids in probe.seen if e == 0] != [ids for e, ids in probe.seen if e == 1]
    assert probe.val_rows == 2 * len(_stored(data["ol"], "val"))
    assert dm.stats is not None and dm.scenario_name == "data-fake"


def test_setup_twice_hashes_each_shard_once(data: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """Training calls setup("fit") before Lightning does: the second call must not re-read every shard."""
    import ttompc.data.datamodule as dm_module

    calls: list[str] = []
    real = dm_module.verify_shard
    monkeypatch.setattr(dm_module, "verify_shard", lambda path, sha: calls.append(str(path)) or real(path, sha))
    dm = _dm(data)
    first = list(calls)
    dm.setup("fit")
    assert first and calls == first and len(set(first)) == len(first)
