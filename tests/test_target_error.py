"""The target-error diagnostic (``ttompc evaluate target``): a provider that plans exactly as the expert does, its
target shifted by a known offset, has zero raw error and the offset's scaled norm as blended error; the report's
aggregation and correlations on hand-computed numbers; the command end to end."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import mpc_fakes
import numpy as np
import pytest

from ttompc.cli import main
from ttompc.evaluation.measurement import Measurement
from ttompc.evaluation.problems import EvalProblem
from ttompc.evaluation.target_error import TargetErrorConfig, expert_episodes
from ttompc.evaluation.target_error_report import ERRORS, bucket_label, correlation, summarize
from ttompc.mpc.expert import Expert, ExpertRollout
from ttompc.mpc.loop import MPCRun
from ttompc.mpc.plant import PlantNoise
from ttompc.mpc.providers import WarmStart
from ttompc.mpc.settings import MPCSettings
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.scp import TerminalCost

SHORT = mpc_fakes.FreeFlyerShort.name


class ExpertPlanProvider:
    """Plans every window with the expert's own plan from the measured state (a second ``Expert`` beside the
    diagnostic's, fed the same history), its terminal target that plan's state at the window's end + ``offset``."""

    name, role = "EXPERT-PLAN", "baseline"

    def __init__(self, ep: EvalProblem, offset: np.ndarray, settings: MPCSettings) -> None:
        self.ep, self.offset, self.settings = ep, offset, settings

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        N = problem.n_steps
        draws = (self.ep.index, self.ep.seed, problem, self.ep.rel, 10)
        self.rollout = ExpertRollout.start(
            scenario, draws, np.zeros(N, bool), np.ones(N, bool), PlantNoise(), self.settings
        )
        self.expert = Expert(scenario, [self.rollout], None, self.settings.backend)
        self.scenario = scenario

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        self.t = window.start
        self.expert.before(self.t, [], [x])
        plan = self.rollout.plans[self.t]
        X, U = plan.X[: window.length + 1].copy(), plan.U[: window.length].copy()
        terminal = None if window.reaches_end else TerminalCost(X[-1] + self.offset, self.scenario.mpc.tracking)
        return WarmStart(X, U, terminal)

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> None:
        self.expert.after(self.t, [SimpleNamespace(u=u)], [x_next])  # type: ignore[list-item]


def test_a_target_offset_from_the_expert_plan_is_measured_exactly() -> None:
    """The raw target and the provider's first control are the expert's (error 0), the blended target is off by the
    offset, ‖δ / state_scale‖₂; windows that reach N have no target; ``every`` = 3 subsamples the expert steps."""
    sc = get_scenario(SHORT)
    settings = MPCSettings()
    eps = Measurement(problems=2).problem_set(sc)
    offset = 0.05 * sc.state_units() * np.arange(1, sc.state_dim + 1) / sc.state_dim
    expected = float(np.linalg.norm(offset / sc.state_units()))
    H, T = 10, 12
    run = MPCRun(H, settings, max_steps=T)
    episodes, rows = expert_episodes(sc, eps, [ExpertPlanProvider(ep, offset, settings) for ep in eps], run, every=3)
    assert [len(e.U) for e in episodes] == [T, T]
    for ep_rows in rows:
        assert [r["t"] for r in ep_rows] == [0, 3, 6, 9] and not any(r["expert_fallback"] for r in ep_rows)
        for r in ep_rows:
            assert r["to_go"] == sc.n_steps - r["t"]
            assert r["target_raw"] == pytest.approx(0.0, abs=1e-12) and r["control_raw"] == pytest.approx(0, abs=1e-12)
            assert r["target_blended"] == pytest.approx(expected, rel=1e-9)
            assert np.isfinite(r["control"])


def test_windows_that_reach_the_end_have_no_target() -> None:
    sc = get_scenario(SHORT)
    settings = MPCSettings()
    (ep,) = Measurement(problems=1).problem_set(sc)
    N, H = sc.n_steps, 10
    run = MPCRun(H, settings)
    _, (rows,) = expert_episodes(sc, [ep], [ExpertPlanProvider(ep, np.zeros(sc.state_dim), settings)], run, every=7)
    assert [r["t"] for r in rows] == list(range(0, N, 7))
    for r in rows:
        assert np.isfinite(r["target_raw"]) == (r["to_go"] > H) and np.isfinite(r["control"])


def test_summary_buckets_and_correlations_by_hand() -> None:
    assert [bucket_label(k) for k in (1, 5, 6, 11, 50, 51, 100, 101)] == [
        "1-5",
        "1-5",
        "6-10",
        "11-20",
        "21-50",
        "51-100",
        "51-100",
        "101+",
    ]
    c = correlation([1.0, 2.0, 3.0, 4.0], [1.0, 8.0, 27.0, 64.0])  # monotone, not linear
    assert c["spearman"] == pytest.approx(1.0) and 0.9 < c["pearson"] < 1.0 and c["n"] == 4
    assert np.isnan(correlation([1.0, 2.0], [3.0, 4.0])["pearson"])  # n < 3
    c = correlation([1.0, 2.0, 3.0, np.nan], [3.0, 2.0, 1.0, 0.0])  # pairs with a nan are left out
    assert (c["pearson"], c["spearman"], c["n"]) == (pytest.approx(-1.0), pytest.approx(-1.0), 3)
    nan = float("nan")

    def step(p: int, t: int, raw: float) -> dict[str, Any]:
        return {
            "problem": p,
            "plant": "nominal",
            "horizon": 10,
            "t": t,
            "to_go": 40 - t,
            "expert_fallback": False,
            "target_raw": raw,
            "target_blended": raw / 2,
            "control": 1.0,
            "control_raw": nan,
        }

    steps = [step(0, 0, 1.0), step(0, 25, 3.0), step(1, 0, 2.0), step(1, 25, 6.0), step(2, 0, 4.0)]
    recs = [
        {
            "problem": p,
            "plant": "nominal",
            "horizon": 10,
            "feasible": p < 2,
            "rel_increment": inc,
            "expert_fallbacks": 0,
            **{k: m for k, m in zip(ERRORS, means, strict=True)},
        }
        for p, inc, means in [
            (0, 0.1, (2.0, 1.0, 1.0, nan)),
            (1, 0.3, (4.0, 2.0, 1.0, nan)),
            (2, nan, (4.0, 2.0, 1.0, nan)),
        ]
    ]
    (g,) = summarize(recs, steps)
    assert (g["episodes"], g["feasible"], g["expert_steps"]) == (3, 2, 5)
    assert list(g["buckets"]) == ["21-50", "11-20"]  # by steps to go, the longest first
    assert g["buckets"]["21-50"]["target_raw"] == {"mean": pytest.approx(7 / 3), "median": 2.0, "n": 3}
    assert g["buckets"]["11-20"]["target_blended"]["mean"] == pytest.approx(2.25)
    assert g["all"]["control_raw"]["n"] == 0 and g["rel_increment"]["mean"] == pytest.approx(0.2)
    assert g["correlation"]["target_raw"]["n"] == 2  # the infeasible episode has no cost


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return mpc_fakes.tiny_planner().save(tmp_path_factory.mktemp("planner") / "bundle")


@pytest.mark.slow
def test_evaluate_target_command(tmp_path: Path, bundle: Path) -> None:
    """The command on both plants with a (random) model: a report per plant, its files, the expert steps every
    ``every``; bad input is one line, exit code 2."""
    out = tmp_path / "target"
    rc = main(
        [
            "evaluate",
            "target",
            "--model",
            str(bundle),
            "problems=2",
            "max_steps=6",
            "every=2",
            "workers=1",
            "plants=[nominal,perturbed]",
            "plot=true",
            f"out={out}",
        ]
    )
    assert rc == 0
    report = json.loads((out / "target_error.json").read_text())
    assert report["method"] == "R-TTO-MPC" and [(g["plant"], g["horizon"]) for g in report["summary"]] == [
        ("nominal", 10),
        ("perturbed", 10),
    ]
    assert len(report["episodes"]) == 4 and all(
        g["expert_steps"] + g["expert_fallbacks"] == 6 for g in report["summary"]
    )
    assert "| nominal | 10 | 51-100 |" not in (out / "target_error.md").read_text()  # N = 40: no such bucket
    assert "| perturbed | 10 | all |" in (out / "target_error.md").read_text()
    assert (out / "target_error_steps.csv").stat().st_size > 0 and (out / "target_error.png").stat().st_size > 0
    assert main(["evaluate", "target", f"scenario={SHORT}", "method=TTO-MPC", f"out={out}"]) == 2  # no model
    assert main(["evaluate", "target", f"scenario={SHORT}", "method=NOPE", f"out={out}"]) == 2
    assert main(["evaluate", "target", f"scenario={SHORT}", "every=0", f"out={out}"]) == 2
    cfg = TargetErrorConfig(model="m", ft_model="f", scenario=SHORT)
    assert cfg.method_entry().name == "R-FT-TTO-MPC"
    assert TargetErrorConfig(model="m", robust_blend=0.0, scenario=SHORT).method_entry().name == "TTO-MPC"
