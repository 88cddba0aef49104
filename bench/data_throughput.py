"""Data pipeline throughput: dataset generation (problems/s per scenario, real REL→SCP solves) and
``TrajectoryDataModule`` streaming (samples/s on synthetic shards written through the real pipeline).

    .venv/bin/python bench/data_throughput.py [--problems 8] [--rows 6000] [--workers 1]

Generation runs the default backend and the previous default (backend="conic") on the same problems (free-flyer,
quadrotor) for a same-run speed-up.

Prints one JSON line and writes it to ``bench/results/data_throughput.json``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from record import Machine, result_path, write_result  # noqa: E402

from ttompc.data.config import DataConfig, GenerateConfig, SplitConfig  # noqa: E402
from ttompc.data.generate import generate  # noqa: E402
from ttompc.data.schema import trajectory_features  # noqa: E402
from ttompc.data.shards import ShardWriter, read_shard  # noqa: E402
from ttompc.scenarios import get_scenario, list_scenarios  # noqa: E402
from ttompc.scenarios.base import Problem, Scenario, Window  # noqa: E402
from ttompc.solvers.scp import SCPResult, SCPStatus  # noqa: E402
from ttompc.version import code_version  # noqa: E402


def synthetic_solve(scenario: Scenario, problem: Problem, **kwargs: Any) -> tuple[SCPResult, SCPResult]:
    """Random controls rolled out with the scenario's dynamics: realistic shapes at no solver cost."""
    rng = np.random.default_rng(abs(hash(problem.x0.tobytes())) % 2**32)
    results = []
    for _ in range(2):
        U = rng.normal(scale=1e-3, size=(scenario.n_steps, scenario.control_dim))
        X = scenario.rollout(problem, U)
        results.append(SCPResult(SCPStatus.OPTIMAL, X, U, scenario.cost(U), 0.0, 1, 0.0, 0.0, Window.full(problem)))
    return results[0], results[1]


def bench_generation(problems: int, workers: int, tmp: Path) -> dict[str, Any]:
    """Problems/s of ``generate`` with the default backend and with the previous default (``backend="conic"``:
    QOCO/Clarabel, 2-norm trust region) on the same seeded problems, alternating, in the same run."""
    out: dict[str, Any] = {}
    for name in list_scenarios():
        try:
            get_scenario(name)
        except ImportError as err:  # scenario module not written yet
            out[name] = {"skipped": str(err)}
            continue
        rows: dict[str, Any] = {}
        backends = {"default": None, "conic": "conic"} if name in ("freeflyer", "quadrotor") else {"default": None}
        for label, backend in backends.items():
            cfg = GenerateConfig(
                scenario=name,
                problems=problems,
                out=str(tmp / f"gen-{name}-{label}"),
                shard_size=problems,
                workers=workers,
                backend=backend,
                splits=SplitConfig(train=1.0, val=0.0, test=0.0),  # timing only: every problem in one split
                card_dir=None,
            )
            t0 = time.perf_counter()
            manifest = generate(cfg, progress=False)
            dt = time.perf_counter() - t0
            rows[label] = {
                "problems": problems,
                "workers": workers,
                "seconds": round(dt, 2),
                "problems_per_s": round(problems / dt, 3),
                "failures": manifest["counts"]["failures"],
                "mean_solve_time_s": {s: v["mean_solve_time"] for s, v in manifest["solver"].items()},
                "mean_iterations": {s: v["mean_iterations"] for s, v in manifest["solver"].items()},
            }
        if "conic" in rows:
            rows["speedup_vs_conic"] = round(rows["default"]["problems_per_s"] / rows["conic"]["problems_per_s"], 2)
        out[name] = rows
    return out


def bench_datamodule(rows_total: int, tmp: Path, batches: int = 60) -> dict[str, Any]:
    from ttompc.data.datamodule import TrajectoryDataModule

    root = tmp / "synthetic"
    cfg = GenerateConfig(
        scenario="freeflyer",
        problems=rows_total // 2,
        out=str(root),
        shard_size=500,
        workers=1,
        solver="bench.data_throughput:synthetic_solve",
        card_dir=None,
    )
    generate(cfg, progress=False)
    dagger = tmp / "dagger"  # the same rows relabelled as DAgger rows, written through the shared writer
    writer = ShardWriter(dagger, trajectory_features(get_scenario("freeflyer")))
    for k, f in enumerate(sorted((root / "train").glob("*.parquet"))):
        rows = [dict(r, source="dagger", iteration=0) for r in read_shard(f).with_format("numpy")]
        writer.write(rows, k)
    result: dict[str, Any] = {"rows": rows_total, "batch_size": 256, "context_length": 100}
    for label, workers, dirs in (("workers0", 0, []), ("workers2", 2, []), ("mix0.7_workers0", 0, [str(dagger)])):
        dm = TrajectoryDataModule(
            DataConfig(
                paths=[str(root)],
                dagger_dirs=dirs,
                open_loop_fraction=0.7,
                batch_size=256,
                num_workers=workers,
                train_batches_per_epoch=batches + 5,
            )
        )
        dm.setup("fit")
        it = iter(dm.train_dataloader())
        for _ in range(5):  # warm-up: worker start, pool fill
            next(it)
        t0 = time.perf_counter()
        n = sum(len(next(it)["problem_id"]) for _ in range(batches))
        result[f"samples_per_s_{label}"] = round(n / (time.perf_counter() - t0))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=8, help="problems per scenario for generation")
    parser.add_argument("--workers", type=int, default=1, help="generation workers")
    parser.add_argument("--rows", type=int, default=6000, help="synthetic rows for the DataModule")
    args = parser.parse_args()
    machine = Machine()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        result = {
            "bench": "data_throughput",
            "code_version": code_version(),
            "generation": bench_generation(args.problems, args.workers, tmp),
            "datamodule": bench_datamodule(args.rows, tmp),
        }
    write_result({**result, **machine.record()}, result_path("data_throughput"))


if __name__ == "__main__":
    main()
