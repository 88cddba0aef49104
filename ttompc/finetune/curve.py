"""The learning curve of a DAgger run: per iteration, the closed loop on fixed selection problems (nominal and
perturbed plants, paired against the pretrained model), the imitation loss on held-out closed-loop rows (the first
iteration's validation rows, one set for every model), the labels aggregated so far and the compute spent; and its
figure.

``measure_curve`` reads ``<run>/dagger_state.json`` and each iteration's planner (``<run>/iter-<i>/planner``), and
appends one record per model to ``<run>/curve.json`` (TTO-MPC) or, with ``--robust-blend`` > 0, to
``<run>/curve-robust.json`` (R-TTO-MPC, the method the headlines report) (resumable: measured models are skipped), so
a curve can be measured while the run goes on. ``curve_figure`` draws one or more runs' curves, each method's that
was measured.

    python -m ttompc.finetune.curve measure RUN --data DATA [--problems 50 --seed 1001 --protocol recommended]
    python -m ttompc.finetune.curve measure RUN --data DATA --robust-blend 0.95
    python -m ttompc.finetune.curve figure RUN [RUN ...] --out docs/figures/dagger_curve.png
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ttompc.data.shards import atomic_write_json
from ttompc.evaluation.stats import paired_points
from ttompc.mpc.episode import rel_increment
from ttompc.mpc.methods import model_method

if TYPE_CHECKING:
    from ttompc.policy import Planner

# the curve file of each method measured: the TTO model slot's method (``closed_loop_metrics``), plain or robust
CURVE_FILES = {
    model_method("TTO", robust).name: "curve-robust.json" if robust else "curve.json" for robust in (False, True)
}
PLANTS = ("nominal", "perturbed")


def _models(run: Path) -> list[tuple[int, Path]]:
    """(iteration, planner dir) of the pretrained model (−1) and of every finished iteration."""
    state = json.loads((run / "dagger_state.json").read_text())
    return [(-1, run / "source-planner")] + [(r["iteration"], Path(r["planner"])) for r in state["completed"]]


def _labels(run: Path, iteration: int) -> dict[str, int]:
    """Rollouts and label rows collected in iterations 0..``iteration`` (their shard records)."""
    rollouts = rows = 0
    for i in range(iteration + 1):
        for meta in sorted((run / "dagger" / f"iter-{i:03d}" / "meta").glob("shard-*.json")):
            m = json.loads(meta.read_text())
            rollouts, rows = rollouts + int(m.get("rollouts", 0)), rows + int(m.get("rows", 0))
    return {"rollouts": rollouts, "labels": rows}


def imitation_loss(planner: Planner, data: Sequence[str], dagger_dirs: Sequence[str], batches: int = 20) -> float:
    """The teacher-forced training loss (action + next state, MSE) of ``planner`` on the held-out closed-loop rows
    (the DAgger folders' val split; ``data``: the run's open-loop dataset, whose manifest the loader reads), over at
    most ``batches`` batches of 32."""
    import torch

    from ttompc.data.config import DataConfig
    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.data.shards import ShardError
    from ttompc.training.module import masked_mse

    cfg = DataConfig(paths=list(data), dagger_dirs=list(dagger_dirs), batch_size=32, verify_checksums=False)
    dm = TrajectoryDataModule(cfg)
    dm.setup("validate")
    dm.use_stats(planner.stats)
    try:
        loader = dm.dagger_val_dataloader()
    except ShardError:  # no held-out closed-loop rows (collect.val_fraction = 0)
        return float("nan")
    model = planner.model.eval()
    losses = []
    with torch.no_grad():
        for k, b in enumerate(loader):
            if k >= batches:
                break
            a, s = model(b["goals"], b["rtg"], b["ctg"], b["states"], b["actions"], b["timesteps"])
            mask = b.get("mask")
            loss = masked_mse(a, b["target_actions"], mask) + masked_mse(
                s, b["target_next_states"], b.get("state_mask", mask)
            )
            losses.append(float(loss))
    return float(np.mean(losses)) if losses else float("nan")


def _closed_loop(planner: Planner, measurement: Any, problems: list[Any]) -> tuple[dict[str, float], np.ndarray]:
    """Closed-loop metrics and the per-problem (J − J_REL)/J_REL (nan where infeasible) of the measurement's
    method (TTO-MPC, or R-TTO-MPC with its ``robust_blend``)."""
    from ttompc.evaluation.episodes import closed_loop_metrics
    from ttompc.parallel import single_torch_thread

    with single_torch_thread():
        metrics, episodes = closed_loop_metrics(planner, measurement, problems)
    inc = np.array([rel_increment(e.cost, e.rel_cost, e.feasible) for e in episodes])
    return metrics, inc


def measure_curve(
    run: Path,
    data: Sequence[str] = (),
    problems: int = 50,
    seed: int = 1001,
    protocol: str = "recommended",
    horizon: int = 10,
    max_steps: int | None = None,
    robust_blend: float = 0.0,
) -> list[dict[str, Any]]:
    """Measure every model of ``run`` not yet in its method's curve file (TTO-MPC, or R-TTO-MPC when
    ``robust_blend`` > 0; see the module doc; ``data``: the run's
    open-loop dataset folders, for the imitation loss, nan without them or without held-out closed-loop rows;
    ``max_steps``: shorter episodes, for smoke runs); returns the records."""
    from ttompc.evaluation.measurement import Measurement
    from ttompc.policy import Planner

    path = run / CURVE_FILES[model_method("TTO", robust_blend > 0).name]
    records: list[dict[str, Any]] = json.loads(path.read_text()) if path.is_file() else []
    done = {r["iteration"] for r in records}
    state = json.loads((run / "dagger_state.json").read_text())
    seconds = {r["iteration"]: r.get("seconds", {}) for r in state["completed"]}
    baseline = {p: r["increments"][p] for r in records if r["iteration"] == -1 for p in PLANTS}
    sets: dict[str, tuple[Measurement, list[Any]]] = {}
    for iteration, planner_dir in _models(run):
        if iteration in done:
            continue
        planner = Planner.from_pretrained(planner_dir)
        record: dict[str, Any] = {
            "iteration": iteration,
            "planner": str(planner_dir),
            "increments": {},
            "seconds": seconds.get(iteration, {}),
            **_labels(run, iteration),
        }
        for plant in PLANTS:
            if plant not in sets:
                m = Measurement(
                    protocol=protocol,
                    problems=problems,
                    seed=seed,
                    horizons=[horizon],
                    plants=[plant],
                    max_steps=max_steps,
                    robust_blend=robust_blend,
                )
                sets[plant] = (m, m.problem_set(planner.scenario))
            m, probs = sets[plant]
            metrics, inc = _closed_loop(planner, m, probs)
            keys = ("feasible_rate", "truncated", "cost_increment", "cost_increment_se")  # truncated: cut at max_steps
            record[plant] = {k: metrics[k] for k in keys}
            record["increments"][plant] = [None if math.isnan(v) else float(v) for v in inc]
            if iteration == -1:
                baseline[plant] = record["increments"][plant]
            record[plant]["vs_pretrained"] = paired_points(record["increments"][plant], baseline[plant])
        # one fixed held-out set for every model: the first iteration's val rows (never trained on)
        dirs = [str(run / "dagger" / "iter-000")] if state["completed"] else []
        record["imitation_loss"] = imitation_loss(planner, data, dirs) if dirs and data else float("nan")
        records.append(record)
        records.sort(key=lambda r: r["iteration"])
        atomic_write_json(path, records)
    return records


def curve_figure(runs: Sequence[Path], out: Path) -> Path:
    """One row per run (a scenario per run, each on its own cost scale): the closed-loop cost paired against the
    pretrained model (± one standard error) and the goals per iteration on both plants, for each method measured
    (``CURVE_FILES``), and the imitation loss on held-out closed-loop rows. A run with no measured curve file
    raises ``FileNotFoundError``."""
    from ttompc.evaluation.plots import row_figure

    return row_figure(runs, _run_row, out, size=(13, 3.6))


def _run_row(run: Path, axes: Sequence[Any]) -> None:
    """The three panels of ``curve_figure`` of one run."""
    from matplotlib.ticker import MaxNLocator

    scenario = json.loads((run / "source-planner" / "config.json").read_text())["scenario"]["name"]
    files = {method: run / name for method, name in CURVE_FILES.items() if (run / name).is_file()}
    if not files:
        raise FileNotFoundError(f"{run} has no measured curve ({', '.join(CURVE_FILES.values())})")
    for (method, path), marker in zip(files.items(), ("o", "s"), strict=False):
        recs = json.loads(path.read_text())
        it = np.array([r["iteration"] for r in recs]) + 1  # 0: the pretrained model
        for plant, style in zip(PLANTS, ("-", "--"), strict=True):
            mean = np.array([r[plant]["vs_pretrained"]["mean"] for r in recs]) * 100
            se = np.array([r[plant]["vs_pretrained"]["se"] for r in recs]) * 100
            label = f"{method}, {plant}"
            axes[0].errorbar(it, mean, yerr=np.nan_to_num(se), ls=style, marker=marker, capsize=3, label=label)
            axes[1].plot(it, [r[plant]["feasible_rate"] for r in recs], ls=style, marker=marker, label=label)
    axes[2].plot(it, [r["imitation_loss"] for r in recs], marker="o")
    axes[0].axhline(0, color="k", lw=0.5)
    titles = ("closed-loop cost vs pretrained, points of J_REL", "goals reached", "imitation loss, held-out rows")
    for ax, title in zip(axes, titles, strict=True):
        ax.set_title(f"{scenario}: {title}", fontsize=10)
        ax.set_xlabel("DAgger iteration (0: pretrained)")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    for ax in axes[:2]:
        ax.legend(fontsize=7)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ttompc.finetune.curve", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="action", required=True)
    m = sub.add_parser("measure", help="measure a run's models not yet in <run>/curve.json")
    m.add_argument("run", type=Path)
    m.add_argument("--data", nargs="*", default=[], help="the run's open-loop dataset folders (imitation loss)")
    m.add_argument("--problems", type=int, default=50)
    m.add_argument("--seed", type=int, default=1001, help="root seed of the selection problems (default 1001)")
    m.add_argument("--protocol", default="recommended")
    m.add_argument("--horizon", type=int, default=10)
    m.add_argument("--robust-blend", type=float, default=0.0, help="> 0: measure R-TTO-MPC with this target blend")
    f = sub.add_parser("figure", help="draw the curves of measured runs")
    f.add_argument("runs", type=Path, nargs="+")
    f.add_argument("--out", type=Path, default=Path("docs/figures/dagger_curve.png"))
    a = p.parse_args(argv)
    if a.action == "measure":
        for r in measure_curve(a.run, a.data, a.problems, a.seed, a.protocol, a.horizon, robust_blend=a.robust_blend):
            print(json.dumps({k: r[k] for k in ("iteration", "nominal", "perturbed", "imitation_loss", "labels")}))
    else:
        print(curve_figure(a.runs, a.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
