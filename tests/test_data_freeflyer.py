"""End to end on the real free-flyer scenario and SCP engine: a few problems with two spawned workers."""

from __future__ import annotations

from pathlib import Path

import helpers
import numpy as np

from ttompc.data.config import DataConfig
from ttompc.data.datamodule import TrajectoryDataModule
from ttompc.data.schema import problem_from_row
from ttompc.data.shards import read_shard
from ttompc.scenarios import get_scenario
from ttompc.seeding import problem_seed


def test_freeflyer_generation_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "freeflyer-mini"
    manifest = helpers.tiny_dataset(out, "freeflyer", 4, (0.5, 0.25, 0.25), shard_size=2, seed=11, workers=2)
    sc = get_scenario("freeflyer")
    rows = [r for f in sorted(out.glob("*/*.parquet")) for r in read_shard(f).with_format("numpy")]
    assert len(rows) + sum(f["stage"] in ("rel", "scp") for f in manifest["failures"]) >= 4
    assert manifest["counts"]["rows"]["total"] == len(rows) > 0
    assert {tuple(r["states"].shape) for r in rows} == {(101, 6)}
    for r in rows:
        problem = problem_from_row(sc, r)
        expected = sc.sample(np.random.default_rng(problem_seed(11, int(r["problem_id"]))))
        np.testing.assert_allclose(problem.x0, expected.x0)
        helpers.assert_rtg_ctg_by_hand(sc, problem, r, rtol=1e-4)
        assert r["status"] in ("optimal", "feasible") and r["iterations"] >= 1 and r["solve_time"] > 0
    scp = [r for r in rows if r["source"] == "scp"]
    assert all(r["ctg"][0] == 0 for r in scp), "successful SCP trajectories avoid the obstacles"
    dm = TrajectoryDataModule(
        DataConfig(paths=[str(out)], batch_size=4, shuffle_pool=8, context_length=20, train_batches_per_epoch=2)
    )
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert dm.scenario_name == "freeflyer" and batch["states"].shape == (4, 20, 6)
