"""The closed-loop learning curve (ttompc.evaluation.scaling_curve): the paired statistic against hand arithmetic,
one selection per curve file, resumable points, and the figure (``plots.row_figure``: a row per curve file)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest

from ttompc.errors import UserError
from ttompc.evaluation.plots import row_figure
from ttompc.evaluation.scaling_curve import Selection, curve_figure, measure_point
from ttompc.evaluation.stats import paired_points


def test_paired_points_pairs_only_problems_both_finish() -> None:
    model = [0.5, None, 0.3, 0.9]
    base = [0.2, 0.4, None, 0.1]
    r = paired_points(model, base)
    # pairs: problem 0 (0.3) and problem 3 (0.8): mean 0.55, sd = 0.3536, se = sd / sqrt(2) = 0.25
    assert r["n"] == 2 and r["goals"] == 3 and r["baseline_goals"] == 3
    assert r["mean"] == pytest.approx(0.55)
    assert r["se"] == pytest.approx(0.25)


def test_paired_points_refuses_unequal_sets_and_reports_nan_without_pairs() -> None:
    with pytest.raises(ValueError, match="one value per problem"):
        paired_points([0.1], [0.1, 0.2])
    r = paired_points([None], [0.3])
    assert r["n"] == 0 and math.isnan(r["mean"]) and math.isnan(r["se"])


def _curve(tmp_path: Path, sel: Selection) -> Path:
    point = {"label": "a", "n_embd": 128, "n_layer": 3, "params": 600_000, "data_problems": 12_000, "cpu_hours": 0.5}
    for plant in ("nominal", "perturbed"):
        point[plant] = {"increments": [0.4, 0.6], "vs_baseline": paired_points([0.4, 0.6], [0.3, 0.3])}
    state = {
        "selection": sel.__dict__,
        "scenario": "quadrotor",
        "points": [point],
        "baseline": {"nominal": [0.3, 0.3], "perturbed": [0.3, 0.3]},
    }
    path = tmp_path / "curve.json"
    path.write_text(json.dumps(state))
    return path


def test_measured_points_are_skipped_and_other_selections_refused(tmp_path: Path) -> None:
    sel = Selection(problems=2, seed=7)
    path = _curve(tmp_path, sel)
    # an existing label returns its record without loading the (missing) planner
    r = measure_point(path, tmp_path / "no-planner", "a", sel, data_problems=1, cpu_hours=1.0)
    assert r["nominal"]["vs_baseline"]["mean"] == pytest.approx(0.2)
    with pytest.raises(UserError, match="another selection"):
        measure_point(path, tmp_path / "no-planner", "b", Selection(problems=3, seed=7), data_problems=1, cpu_hours=1)


def test_figure_is_drawn_from_a_curve_file(tmp_path: Path) -> None:
    import matplotlib.image

    path = _curve(tmp_path, Selection())
    one = matplotlib.image.imread(curve_figure([path], tmp_path / "fig.png"))
    two = matplotlib.image.imread(curve_figure([path, path], tmp_path / "two.png"))
    assert one.shape[1] == two.shape[1] and two.shape[0] == 2 * one.shape[0]  # a row per curve file
    assert (one[..., :3] < 0.5).any()  # something drawn, not a blank canvas


def test_row_figure_draws_each_row_on_its_own_axes(tmp_path: Path) -> None:
    import matplotlib.image

    seen: list[tuple[int, int]] = []

    def draw(row: int, axes: Sequence[Any]) -> None:
        seen.append((row, len(axes)))
        axes[0].plot([0, 1], [row, row])

    one = row_figure([1], draw, tmp_path / "one.png", size=(6, 2), panels=2)
    two = row_figure([1, 2], draw, tmp_path / "sub" / "two.png", size=(6, 2), panels=2, footer="the command")
    assert seen == [(1, 2), (1, 2), (2, 2)]  # every row drawn once, in order, with its panels
    a, b = matplotlib.image.imread(one), matplotlib.image.imread(two)
    assert a.shape[1] == b.shape[1] == 6 * 110 and (a.shape[0], b.shape[0]) == (2 * 110, 4 * 110)
