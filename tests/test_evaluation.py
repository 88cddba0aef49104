"""Warm-start evaluation, planning-horizon study and their metrics (issues 5 and 6)."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import mpc_fakes
import numpy as np
import pytest

from ttompc.cli import main
from ttompc.evaluation.common import eval_problem
from ttompc.evaluation.horizon import HorizonStudyConfig, run_horizon_study
from ttompc.evaluation.metrics import improvement_by_threshold, normalized_cost_increment
from ttompc.scenarios import get_scenario

SHORT = mpc_fakes.FreeFlyerShort.name


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return mpc_fakes.tiny_planner().save(tmp_path_factory.mktemp("planner") / "bundle")


def test_normalized_cost_increment_per_problem() -> None:
    recs = [
        {"problem": 0, "rel_cost": 1.0, "cost": 1.5},
        {"problem": 0, "rel_cost": 1.0, "cost": 3.0},
        {"problem": 1, "rel_cost": 2.0, "cost": 2.0},
        {"problem": 1, "rel_cost": 2.0, "cost": 6.0},
    ]
    normalized_cost_increment(recs)
    assert [r["norm_cost_increment"] for r in recs] == [0.25, 1.0, 0.0, 1.0]


def test_improvement_by_threshold() -> None:
    rows = [
        {"nonconvexity": 0.0, "rel_cost": 1.0, "REL_cost": 2.0, "REL_iterations": 10, "REL_success": True,
         "TTO_cost": 1.5, "TTO_iterations": 5, "TTO_success": True},
        {"nonconvexity": 1.0, "rel_cost": 1.0, "REL_cost": 3.0, "REL_iterations": 10, "REL_success": True,
         "TTO_cost": 2.0, "TTO_iterations": 10, "TTO_success": True},
        {"nonconvexity": 1.0, "rel_cost": 1.0, "REL_cost": 9.0, "REL_iterations": 1, "REL_success": True,
         "TTO_cost": 9.0, "TTO_iterations": 1, "TTO_success": False},
    ]  # fmt: skip
    out = improvement_by_threshold(rows, ["TTO"], "REL", [0.0, 0.5])
    assert out[0]["count"] == 2 and out[0]["TTO_subopt_improvement"] == pytest.approx(100 * (1 - 0.75 / 1.5))
    assert out[0]["TTO_iterations_improvement"] == pytest.approx(25.0)
    assert out[1]["count"] == 1 and out[1]["TTO_subopt_improvement"] == pytest.approx(50.0)


def test_eval_problems_are_seeded_and_nonconvex() -> None:
    sc = get_scenario(SHORT)
    a = eval_problem(sc, 7, 0, nonconvex_only=True)
    b = eval_problem(sc, 7, 0, nonconvex_only=True)
    assert a.ctg0 > 0 and a.seed == b.seed
    np.testing.assert_array_equal(a.problem.x0, b.problem.x0)
    assert eval_problem(sc, 8, 0).seed != a.seed


def test_horizon_study_report(tmp_path: Path, bundle: Path) -> None:
    cfg = HorizonStudyConfig(
        scenario=SHORT,
        out=str(tmp_path),
        checkpoint=str(bundle),
        ft_checkpoint=str(bundle),
        horizons=[10, 40, 200],
        problems=2,
        workers=2,  # spawn pool: workers import the test scenario and load the model once
        max_steps=3,
    )
    report = run_horizon_study(cfg)
    methods = {"REL-MPC", "DIST-MPC", "TTO-MPC", "FT-TTO-MPC"}
    assert {(r["method"], r["horizon"]) for r in report["summary"]} == {(m, h) for m in methods for h in (10, 40)}
    saved = json.loads((tmp_path / "horizon.json").read_text())
    for r in saved["runs"]:
        for key in ("cost", "rel_cost", "norm_cost_increment", "feasible", "terminal_error", "keepout_violations",
                    "mean_step_time", "max_step_time", "fallbacks", "ctg0", "seed"):  # fmt: skip
            assert key in r
        assert r["steps"] == 3 and r["ctg0"] > 0 and r["max_step_time"] >= r["mean_step_time"] > 0
    with open(tmp_path / "horizon_summary.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(saved["runs"]) == 2 * 2 * 4 and {r["problem"] for r in saved["runs"]} == {0, 1}
    assert len(rows) == 8 and {"feasible_rate", "max_step_time", "norm_cost_increment"} <= set(rows[0])
    assert (tmp_path / "horizon_cost.png").stat().st_size > 0 and (tmp_path / "horizon_runtime.png").is_file()


def test_warmstart_cli_report(tmp_path: Path, bundle: Path) -> None:
    out = tmp_path / "ws"
    rc = main(["evaluate", "warmstart", "--checkpoint", str(bundle), "--problems", "2", "--seed", "3",
               "--out", str(out), "--thresholds", "0,0.5"])  # fmt: skip
    assert rc == 0
    report = json.loads((out / "warmstart.json").read_text())
    assert report["scenario"]["name"] == SHORT and [m["method"] for m in report["methods"]] == ["REL", "TTO"]
    for p in report["problems"]:
        for key in ("ctg0", "nonconvexity", "rel_cost", "REL_cost", "REL_iterations", "REL_time", "REL_success",
                    "TTO_success", "TTO_warmstart_time", "TTO_iterations"):  # fmt: skip
            assert key in p
        assert p["REL_success"] and p["REL_suboptimality"] >= -1e-6
    assert [r["threshold"] for r in report["thresholds"]] == [0.0, 0.5]
    assert (out / "warmstart_improvement.png").is_file() and (out / "warmstart_problems.csv").is_file()


def _random_batches(n_batches: int, B: int = 2, L: int = 8) -> Any:
    import torch
    from torch.utils.data import DataLoader

    g = torch.Generator().manual_seed(0)
    out = []
    for _ in range(n_batches):
        r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
        out.append(
            {
                "states": r(B, L, 6), "actions": r(B, L, 3), "goals": r(B, L, 6), "rtg": r(B, L, 1),
                "ctg": r(B, L, 1), "timesteps": torch.arange(L).expand(B, L).clone(),
                "target_actions": r(B, L, 3), "target_next_states": r(B, L, 6), "mask": torch.ones(B, L),
            }
        )  # fmt: skip
    return DataLoader(out, batch_size=None)


def test_closed_loop_callback_logs_metrics(tmp_path: Path) -> None:
    import lightning as L
    from lightning.pytorch.loggers import CSVLogger

    from ttompc.config import to_container
    from ttompc.training.callbacks import ClosedLoopEvalCallback
    from ttompc.training.config import OptimConfig
    from ttompc.training.module import TrajectoryTransformerModule

    planner = mpc_fakes.tiny_planner()
    module = TrajectoryTransformerModule(
        model_config=to_container(planner.model.cfg),
        optim=to_container(OptimConfig(warmup_steps=0)),
        scenario=SHORT,
        scenario_version=planner.scenario.version,
        norm_stats=planner.stats.to_dict(),
        plot_trajectories=False,
    )
    cb = ClosedLoopEvalCallback(problems=1, horizon=5, max_steps=3, every_n_val=2, seed=1)
    trainer = L.Trainer(
        max_epochs=4,
        logger=CSVLogger(str(tmp_path), name="logs", version=""),
        callbacks=[cb],
        default_root_dir=str(tmp_path),
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
        num_sanity_val_steps=0,
        log_every_n_steps=1,
    )
    trainer.fit(module, train_dataloaders=_random_batches(2), val_dataloaders=_random_batches(1))
    assert cb._runs == 4 and module.model.training  # evaluated after validation runs 2 and 4, mode restored
    with open(tmp_path / "logs" / "metrics.csv") as f:
        rows = [r for r in csv.DictReader(f) if r.get("mpc/cost")]
    assert len(rows) == 2
    for key in ("mpc/cost", "mpc/cost_increment", "mpc/feasible_rate", "mpc/step_time_mean", "mpc/step_time_max"):
        assert np.isfinite(float(rows[-1][key]))
    assert float(rows[-1]["mpc/step_time_max"]) >= float(rows[-1]["mpc/step_time_mean"]) > 0
    assert len(list((tmp_path / "plots").glob("mpc_trajectory_*.png"))) == 2


def test_recipe_section_wires_the_callback_into_training(tmp_path: Path) -> None:
    """``callbacks.eval_mpc`` in a training recipe adds the callback to ``train()``."""
    import lightning as L

    from ttompc.training.config import load_train_config
    from ttompc.training.run import train

    planner = mpc_fakes.tiny_planner()

    class RandomData(L.LightningDataModule):
        def setup(self, stage: str | None = None) -> None:
            self.stats, self.scenario_name = planner.stats, SHORT

        def train_dataloader(self) -> Any:
            return _random_batches(2)

        def val_dataloader(self) -> Any:
            return _random_batches(1)

    m = planner.model.cfg
    cfg = load_train_config(
        overrides=[
            f"model.n_embd={m.n_embd}", f"model.n_layer={m.n_layer}", f"model.n_head={m.n_head}",
            f"model.max_steps={m.max_steps}", "trainer.max_steps=2", "trainer.max_epochs=1", "trainer.accelerator=cpu",
            f"trainer.out_dir={tmp_path}", "trainer.export_planner=false", "trainer.log_every_n_steps=1",
            "logger.kind=csv", "logger.plot_trajectories=false", "callbacks.eval_mpc.enabled=true",
            "callbacks.eval_mpc.problems=1", "callbacks.eval_mpc.horizon=5", "callbacks.eval_mpc.max_steps=2",
        ]
    )  # fmt: skip
    train(cfg, RandomData())
    assert "mpc/cost" in (tmp_path / "logs" / "session-0" / "metrics.csv").read_text()
