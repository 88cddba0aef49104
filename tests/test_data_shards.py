"""Shard writer/reader: round trip through the shared schema, atomic writes, clear errors on bad shards."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import data_fakes  # noqa: F401  (registers the fake scenario)
import numpy as np
import pytest

from ttompc.data.schema import make_row, trajectory_features
from ttompc.data.shards import ShardError, ShardWriter, read_shard, sha256_file, write_shard
from ttompc.scenarios import get_scenario


def _rows(n: int, source: str = "scp") -> list[dict]:
    sc = get_scenario("data-fake")
    rng = np.random.default_rng(0)
    rows = []
    for i in range(n):
        p = sc.sample(rng)
        U = rng.normal(size=(sc.n_steps, 3))
        X = sc.rollout(p, U)
        extra = {"iteration": 2, "target_actions": U + 1} if source == "dagger" else {}
        rows.append(
            make_row(
                sc,
                p,
                problem_id=i,
                seed=100 + i,
                source=source,
                states=sc.to_model_states(p, X),
                actions=U,
                states_opt=X,
                cost=sc.cost(U),
                iterations=4,
                status="optimal",
                solve_time=0.5,
                solver_time=0.25,
                violation=1e-7,
                **extra,
            )
        )
    return rows


def test_ctrl_c_during_a_shard_write_is_raised_after_the_shard_is_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A SIGINT that lands while the table is built or written (inside pyarrow/datasets it once surfaced as a
    features mismatch, exit 1) is held: the shard is written whole, then KeyboardInterrupt is raised, and the
    previous SIGINT handler is back."""
    import os
    import signal

    import ttompc.data.shards as shards

    sc = get_scenario("data-fake")
    rows = _rows(3)
    feats = trajectory_features(sc)
    write_table = shards.pq.write_table

    def interrupted_write(table: object, where: str) -> None:
        os.kill(os.getpid(), signal.SIGINT)  # delivered now, in the middle of the write
        write_table(table, where)

    monkeypatch.setattr(shards.pq, "write_table", interrupted_write)
    handler = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        write_shard(rows, tmp_path / "s.parquet", feats)
    assert signal.getsignal(signal.SIGINT) is handler
    assert len(read_shard(tmp_path / "s.parquet")) == len(rows)


def test_round_trip_equals_written_rows(tmp_path: Path) -> None:
    sc = get_scenario("data-fake")
    rows = _rows(5) + _rows(3, "dagger")
    feats = trajectory_features(sc)
    write_shard(rows, tmp_path / "s.parquet", feats)
    back = list(read_shard(tmp_path / "s.parquet").with_format("numpy"))
    assert read_shard(tmp_path / "s.parquet").features == feats
    assert len(back) == len(rows)
    for r, b in zip(rows, back, strict=True):
        for k, v in r.items():
            if isinstance(v, str):
                assert b[k] == v
            else:
                dtype = np.float32 if np.asarray(b[k]).dtype == np.float32 else np.asarray(v).dtype
                np.testing.assert_array_equal(np.asarray(b[k]), np.asarray(v).astype(dtype), err_msg=k)
    assert back[-1]["iteration"] == 2 and back[-1]["source"] == "dagger"
    np.testing.assert_allclose(back[-1]["target_actions"], back[-1]["actions"] + 1, rtol=1e-6)
    assert not list(tmp_path.glob(".*.tmp")), "temporary files must not survive"


def test_shard_writer_layout_and_checksum(tmp_path: Path) -> None:
    writer = ShardWriter(tmp_path / "dagger-it0", trajectory_features(get_scenario("data-fake")))
    info = writer.write(_rows(4, "dagger"), index=3, split="val")
    assert info.path == "val/shard-00003.parquet" and info.rows == 4
    assert info.sha256 == sha256_file(tmp_path / "dagger-it0" / info.path)
    with pytest.raises(ValueError, match="split"):
        writer.path("holdout", 0)


def test_rows_not_matching_schema_are_rejected(tmp_path: Path) -> None:
    rows = _rows(2)
    del rows[1]["ctg"]
    with pytest.raises(ValueError, match=r"row 1 .*missing \['ctg'\]"):
        write_shard(rows, tmp_path / "s.parquet", trajectory_features(get_scenario("data-fake")))
    with pytest.raises(ValueError, match="expected states"):
        sc = get_scenario("data-fake")
        make_row(
            sc,
            sc.sample(np.random.default_rng(0)),
            problem_id=0,
            seed=0,
            source="rel",
            states=np.zeros((3, 6)),
            actions=np.zeros((2, 3)),
        )


def test_corrupt_and_truncated_shards_name_the_file(tmp_path: Path) -> None:
    path = tmp_path / "train" / "shard-00000.parquet"
    write_shard(_rows(3), path, trajectory_features(get_scenario("data-fake")))
    sha = sha256_file(path)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ShardError, match=rf"{path}.*corrupt.*sha256"):
        read_shard(path, sha)
    path.write_bytes(bytes(data[: len(data) // 3]))
    with pytest.raises(ShardError, match=rf"{path}.*truncated or corrupt"):
        read_shard(path)
    with pytest.raises(ShardError, match=rf"{tmp_path / 'nope.parquet'}.*missing"):
        read_shard(tmp_path / "nope.parquet")


def test_import_ttompc_data_does_not_import_lightning_or_datasets() -> None:
    code = "import sys, ttompc.data; print(any(m in sys.modules for m in ('lightning', 'datasets')))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_sharded_folder_resume_contract(tmp_path: Path) -> None:
    from ttompc.data.distributed import RankInfo
    from ttompc.data.resumable import ShardedFolder

    feats = trajectory_features(get_scenario("data-fake"))
    folder = ShardedFolder(tmp_path, feats, total=7, shard_size=3)
    assert folder.n_shards == 3 and folder.item_range(2) == (6, 7) and folder.items([0, 2]) == [0, 1, 2, 6]
    assert folder.mine(RankInfo(1, 2)) == [1] and folder.pending(RankInfo(0, 2)) == [0, 2]
    groups = list(folder.group([0, 2], iter("abcd")))
    assert [(k, batch) for k, batch, _ in groups] == [(0, ["a", "b", "c"]), (2, ["d"])]
    rows = _rows(3)
    meta = folder.write(0, {"train": rows[:2], "val": rows[2:]}, note="x")
    assert (meta["start"], meta["stop"], meta["note"]) == (0, 3, "x") and folder.done(0) and not folder.done(1)
    assert folder.missing() == [1, 2] and not folder.wait(0.0)
    # rewriting with an empty split removes its stale file; a corrupted file undoes "done"
    folder.write(0, {"train": rows})
    assert not (tmp_path / "val" / "shard-00000.parquet").exists() and folder.done(0)
    (tmp_path / "train" / "shard-00000.parquet").write_bytes(b"broken")
    assert not folder.done(0)
    # the same folder read with another item count: shard 2 covers another range, so it is not done
    folder.write(2, {"train": rows[:1]})
    assert folder.done(2) and not ShardedFolder(tmp_path, feats, total=8, shard_size=3).done(2)
    assert ShardedFolder(tmp_path, feats, total=3, shard_size=3).beyond() == ["shard-00002.json"]
    with pytest.raises(ValueError, match="unknown splits"):
        folder.write(1, {"holdout": rows})
