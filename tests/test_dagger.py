"""DAgger fine-tuning (issue 6, Alg. 1) end to end on the short free-flyer with a tiny model."""

from __future__ import annotations

import json
from pathlib import Path

import mpc_fakes
import numpy as np
import pytest

from ttompc.data.config import DataConfig, GenerateConfig, SplitConfig
from ttompc.data.distributed import RankInfo
from ttompc.finetune.config import ExplorationConfig, FinetuneConfig, load_finetune_config
from ttompc.finetune.dagger import collect_iteration, expert_schedule, finetune, rollout_seed, shard_done
from ttompc.policy.stats import NormStats
from ttompc.scenarios import get_scenario

SHORT = mpc_fakes.FreeFlyerShort.name
RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def test_recipes_load() -> None:
    for path in sorted(RECIPES.glob("*/finetune*.yaml")):
        cfg = load_finetune_config(path)
        assert cfg.dagger.iterations >= 1 and 0 < cfg.data.open_loop_fraction <= 1


def test_cli_takes_overrides_before_and_after_from(capsys: pytest.CaptureFixture[str]) -> None:
    from ttompc.cli import main

    recipe = str(RECIPES / "freeflyer" / "finetune-tiny.yaml")
    for argv in (["--from", "m", "dagger.iterations=7"], ["dagger.iterations=7", "--from", "m"]):
        assert main(["finetune", recipe, *argv, "--print-config"]) == 0
        assert json.loads(capsys.readouterr().out)["dagger"]["iterations"] == 7
    assert main(["finetune", recipe, "dagger.nope=1"]) == 2


def test_expert_schedule_and_seeds() -> None:
    for s in range(20):
        mask = expert_schedule(np.random.default_rng(s), 100, ExplorationConfig())
        assert mask[-1] and 11 <= mask.sum() <= 75  # 1-3 windows, one covering the end
        end_only = expert_schedule(np.random.default_rng(s), 100, ExplorationConfig(windows=[1, 1]))
        start = int(np.argmax(end_only))
        assert end_only[start:].all() and 75 <= start <= 89 and 11 <= end_only.sum() <= 25
    assert rollout_seed(0, 0, 1) != rollout_seed(0, 1, 0) and rollout_seed(0, 2, 3) == rollout_seed(0, 2, 3)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from ttompc.data.generate import generate

    out = tmp_path_factory.mktemp("ol") / "ds"
    cfg = GenerateConfig(
        scenario=SHORT,
        problems=4,
        out=str(out),
        seed=0,
        shard_size=4,
        workers=1,
        splits=SplitConfig(train=0.5, val=0.5, test=0.0),
        card_dir=None,
    )
    assert generate(cfg, progress=False) is not None
    return out


def _config(dataset: Path, run: Path) -> FinetuneConfig:
    cfg = FinetuneConfig()
    d = cfg.dagger
    d.iterations, d.steps_per_iteration = 1, 2
    d.exploration = ExplorationConfig(horizons=[10], windows=[1, 1], window_length=[5, 8])
    d.collect.rollouts, d.collect.shard_size, d.collect.workers, d.collect.val_fraction = 2, 1, 1, 0.0
    d.eval.problems, d.eval.horizon, d.eval.max_steps = 1, 5, 3
    cfg.data = DataConfig(paths=[str(dataset)], batch_size=4, shuffle_pool=8, context_length=10,
                          open_loop_fraction=0.5)  # fmt: skip
    cfg.trainer.out_dir, cfg.trainer.val_check_interval, cfg.trainer.limit_val_batches = str(run), 2, 1
    cfg.trainer.log_every_n_steps, cfg.trainer.accelerator = 1, "cpu"
    cfg.logger.kind = "csv"
    return cfg


def test_one_dagger_iteration_end_to_end_and_resume(tmp_path: Path, dataset: Path) -> None:
    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.data.generate import load_manifest
    from ttompc.policy import Planner

    planner = mpc_fakes.tiny_planner()
    planner = Planner(planner.model, planner.scenario, NormStats.from_dict(load_manifest(dataset)["norm_stats"]))
    source = planner.save(tmp_path / "pretrained")
    run = tmp_path / "run"
    cfg = _config(dataset, run)
    result = finetune(cfg, str(source))

    # state file, checkpoint, exported planner, closed-loop metrics before and after
    state = json.loads((run / "dagger_state.json").read_text())
    assert [it["iteration"] for it in state["completed"]] == [0] and result.iterations == state["completed"]
    it0 = state["completed"][0]
    assert Path(it0["checkpoint"]).is_file() and it0["global_step"] == 2
    assert Planner.from_pretrained(it0["planner"]).extra["dagger_iteration"] == 0
    for m in (state["baseline_metrics"], it0["metrics"]):
        assert {"cost", "cost_increment", "feasible_rate", "step_time_max"} <= set(m)
    assert "dagger/cost" in (run / "logs" / "session-0" / "metrics.csv").read_text()

    # the DataModule reads the DAgger shards back: source, iteration, consistent expert labels
    folder = run / "dagger" / "iter-000"
    dm = TrajectoryDataModule(DataConfig(paths=[str(dataset)], dagger_dirs=[str(folder)], batch_size=6,
                                         shuffle_pool=6, context_length=40, open_loop_fraction=0.0))  # fmt: skip
    dm.setup("fit")
    assert len(dm._dagger["train"]) == 2
    # aggregation ratio: fixed open-loop fraction, or the reference's schedule (9:1 at the first iteration)
    for share, expected in (("fixed", 0.9), ("grow", 0.9)):
        mix = DataConfig(paths=[str(dataset)], dagger_dirs=[str(folder)], context_length=40,
                         open_loop_fraction=0.9, closed_loop_share=share)  # fmt: skip
        mixed = TrajectoryDataModule(mix)
        mixed.setup("fit")
        assert mixed.open_loop_fraction() == pytest.approx(expected)
    batch = next(iter(dm.train_dataloader()))
    assert set(batch["source"].tolist()) == {2}
    assert {int(p) // 10_000_000 for p in batch["problem_id"]} == {0}
    st = dm.stats
    S = st.denormalize("states", batch["states"].double()).numpy()
    A = st.denormalize("actions", batch["target_actions"].double()).numpy()
    S_next = st.denormalize("states", batch["target_next_states"].double()).numpy()
    sc = get_scenario(SHORT)
    np.testing.assert_allclose(S_next, sc.step(None, 0, S, A), atol=2e-5)  # label = f(x_t, u*_t)

    import datasets

    rows = datasets.load_dataset("parquet", data_files=sorted(str(p) for p in folder.glob("train/*.parquet")),
                                 split="train")  # fmt: skip
    assert set(rows["iteration"]) == {0} and set(rows["source"]) == {"dagger"} and len(rows) == 2
    assert all(s.startswith("H=10;") for s in rows["status"])

    # resume: a finished iteration is skipped; a lost shard is recollected identically (seeded rollouts)
    mtimes = {p: p.stat().st_mtime_ns for p in folder.rglob("*.parquet")}
    again = finetune(cfg, str(source))
    assert again.iterations == result.iterations
    assert {p: p.stat().st_mtime_ns for p in folder.rglob("*.parquet")} == mtimes
    before = np.asarray(rows.filter(lambda r: r["problem_id"] == 1)["target_actions"])
    (folder / "meta" / "shard-00001.json").unlink()
    # ranks own disjoint shards: shard 1 belongs to rank 1 of 2, so rank 0 has nothing to redo
    assert collect_iteration(cfg, sc, 0, run / "source-planner", folder, RankInfo(0, 2)) == []
    assert collect_iteration(cfg, sc, 0, run / "source-planner", folder, RankInfo(1, 2)) == [1]
    assert shard_done(folder, 1)
    redo = datasets.load_dataset("parquet", data_files=[str(folder / "train" / "dagger-00001.parquet")], split="train")
    np.testing.assert_array_equal(np.asarray(redo["target_actions"]), before)
