"""Validation-loss curves of the scaling-study runs (docs/scaling.md): reads each run's CSV log (``logger.kind: csv``,
every session of a resumed run), writes ``bench/results/scaling.json`` and ``docs/scaling.png``, prints one JSON line.

    python bench/scaling_curves.py --run ff-2k-0.6m=/root/ttompc-work/runs/ff-2k-0.6m \
        --run ff-4k-0.6m=/root/ttompc-work/runs/ff-4k-0.6m
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from record import result_path, write_result

HERE = Path(__file__).resolve().parent


def val_curve(run_dir: Path) -> list[tuple[int, float]]:
    """(step, val/loss) of every validation of the run, over all its logging sessions (a resumed run has several)."""
    points: dict[int, float] = {}
    for path in sorted(run_dir.glob("logs/*/metrics.csv")):
        with path.open() as f:
            for row in csv.DictReader(f):
                if row.get("val/loss"):
                    points[int(row["step"]) + 1] = float(row["val/loss"])
    if not points:
        raise SystemExit(f"{run_dir}: no validation loss in logs/*/metrics.csv")
    return sorted(points.items())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", action="append", required=True, help="LABEL=RUN_DIR (repeatable)")
    p.add_argument("--plot", default=str(HERE.parent / "docs" / "scaling.png"))
    args = p.parse_args()
    curves = {}
    for item in args.run:
        label, _, path = item.partition("=")
        curves[label] = val_curve(Path(path))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for label, pts in curves.items():
        ax.plot(*zip(*pts, strict=True), marker="o", label=label)
    ax.set(xlabel="optimiser step (batch 32)", ylabel="validation loss", title="free-flyer scaling study")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.plot, dpi=120)
    result = {"bench": "scaling", "curves": {k: [{"step": s, "val_loss": v} for s, v in c] for k, c in curves.items()}}
    write_result(result, result_path("scaling"), {"bench": "scaling", "last": {k: c[-1] for k, c in curves.items()}})


if __name__ == "__main__":
    main()
