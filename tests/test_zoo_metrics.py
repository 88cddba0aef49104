"""Card evaluations are the evaluation reports' numbers, each mean with its standard error and each evaluation with
the command that reproduces it; the model-index is their headline, and a card shows a number at the precision its
standard error supports."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from ttompc.errors import UserError
from ttompc.evaluation.card_metrics import card_metrics
from ttompc.zoo.evaluations import headline_metrics, validate_evaluations
from ttompc.zoo.rounding import format_with_se, round_to_se, shown


def _iv(mean: float, se: float = 0.01) -> dict[str, float]:
    return {"mean": mean, "se": se, "lo": mean - 2 * se, "hi": mean + 2 * se, "n": 10}


WS = {
    "config": {"model": "m-tto", "ft_model": "m-ft", "problems": 10, "seed": 4242, "nonconvex_only": True},
    "command": "ttompc evaluate warmstart --model m-tto --ft-model m-ft problems=10 seed=4242 nonconvex_only=True",
    "methods": [
        {"method": "REL", "runs": 10, "failures": 0, "suboptimality": _iv(0.40), "iterations": _iv(5.8)},
        {
            "method": "TTO",
            "runs": 10,
            "failures": 1,
            "suboptimality": _iv(0.35),
            "iterations": _iv(5.0),
            "gain_share": _iv(0.5),
            "vs_rel": {"suboptimality": _iv(-0.04, 0.02), "iterations": _iv(-0.5, 0.3)},
        },
        {
            "method": "FT-TTO",
            "runs": 10,
            "failures": 0,
            "suboptimality": _iv(0.45),
            "iterations": _iv(7.0),
            "gain_share": _iv(-0.5),
        },
        {"method": "ORACLE", "runs": 10, "failures": 0, "suboptimality": _iv(0.30), "iterations": _iv(6.0)},
    ],
    "complete": True,
}


def _row(plant: str, method: str, feasible: int, inc: float, **extra: object) -> dict[str, object]:
    return {
        "plant": plant,
        "method": method,
        "horizon": 10,
        "feasible": feasible,
        "runs": 4,
        "rel_increment": _iv(inc),
        "mean_step_time": 0.05,
        **extra,
    }


MPC = {
    "config": {
        "model": "m-tto",
        "problems": 4,
        "seed": 4242,
        "horizons": [10],
        "plants": ["nominal", "perturbed"],
        "rtg_scale": None,
        "protocol": "zoo",
        "mpc": {"track": 2.5},
    },
    "command": "ttompc evaluate mpc --model m-tto problems=4 seed=4242 horizons=[10] plants=[nominal,perturbed] "
    "protocol=zoo mpc.track=2.5",
    "summary": [
        _row("nominal", "REL-MPC", 4, 0.9, paper_norm=_iv(0.7)),
        _row("nominal", "TTO-MPC", 2, 0.5),
        _row("nominal", "R-TTO-MPC", 0, float("nan")),
        _row("perturbed", "TTO-MPC", 3, 0.6, vs_rel_mpc=_iv(-0.06, 0.3)),
        _row("nominal", "DIST-MPC", 4, 1.2),
    ],
    "complete": True,
}


def test_metrics_are_the_reports_numbers_with_their_command() -> None:
    evaluations = validate_evaluations(card_metrics("TTO", warmstart=WS, mpc=MPC))
    assert list(evaluations) == ["warmstart", "mpc"]
    ws, mpc = evaluations["warmstart"], evaluations["mpc"]
    m = {**ws["metrics"], **mpc["metrics"]}
    assert m["ws_suboptimality"] == pytest.approx(0.35)
    assert m["ws_suboptimality_rel"] == pytest.approx(0.40)
    assert m["ws_suboptimality_oracle"] == pytest.approx(0.30)
    assert m["ws_gain_share"] == pytest.approx(0.5)
    assert m["ws_suboptimality_vs_rel"] == pytest.approx(-0.04)
    assert m["ws_suboptimality_vs_rel_se"] == pytest.approx(0.02)
    assert m["ws_suboptimality_vs_rel_n"] == 10  # how many problems the paired difference pairs
    assert m["ws_iterations_vs_rel"] == pytest.approx(-0.5)
    # every mean with its standard error, which sets the precision the card shows it at
    assert m["ws_iterations_se"] == m["ws_iterations_rel_se"] == m["ws_gain_share_se"] == pytest.approx(0.01)
    assert m["mpc10_nominal_rel_rel_increment_se"] == m["mpc10_nominal_rel_paper_norm_se"] == pytest.approx(0.01)
    assert m["ws_failures"] == 1
    assert m["mpc10_nominal_model_feasible_rate"] == pytest.approx(0.5)
    assert m["mpc10_nominal_rel_paper_norm"] == pytest.approx(0.7)
    assert m["mpc10_perturbed_model_rel_increment"] == pytest.approx(0.6)
    assert m["mpc10_perturbed_model_vs_rel_mpc"] == pytest.approx(-0.06)
    assert m["mpc10_perturbed_model_vs_rel_mpc_se"] == pytest.approx(0.3)
    assert m["mpc10_perturbed_model_vs_rel_mpc_n"] == 10
    # an undefined mean (no feasible run) is not a value; its feasible rate (0) is
    assert "mpc10_nominal_robust_rel_increment" not in m
    assert m["mpc10_nominal_robust_feasible_rate"] == 0
    assert "DIST" not in json.dumps(list(m))  # only the model, its robust variant, REL, oracle and plan-once
    assert all(math.isfinite(v) for v in m.values())
    assert ws["command"] == WS["command"]  # the command the report records (``ttompc evaluate`` writes it)
    assert ws["what"] == "10 held-out non-convex problems, full-horizon SCP from the TTO, REL and oracle warm starts"
    assert mpc["command"] == MPC["command"]
    assert mpc["what"] == "4 held-out non-convex problems, closed-loop MPC on the nominal and perturbed plants"


def test_metrics_read_rtg_labelled_rows_and_the_headline() -> None:
    """A report run under another rtg mode labels its TTO rows (FT-TTO-MPC[rtg=value]); the card reads them as the
    model's, and takes the headline rows (against REL-MPC at the longest horizon) and REL-MPC's row there. The
    model-index headline is the better variant at H = 10 beside REL-MPC at both horizons."""
    report = {
        "config": {**MPC["config"], "ft_model": "m-ft", "horizons": [10, 30], "protocol": "recommended", "mpc": {}},
        "command": "ttompc evaluate mpc --model m-tto --ft-model m-ft problems=4 seed=4242 horizons=[10,30] "
        "plants=[nominal,perturbed] protocol=recommended",
        "summary": [
            _row("nominal", "FT-TTO-MPC[rtg=value]", 4, 0.3),
            _row("nominal", "REL-MPC", 4, 0.9),
            _row("nominal", "R-FT-TTO-MPC[rtg=value]", 2, 0.1),
            _row("nominal", "REL-MPC", 4, 0.2, horizon=30),
            _row("nominal", "FT-TTO-MPC[rtg=value]", 4, 0.25, horizon=30),
        ],
        "headline": [
            {
                "plant": "nominal",
                "method": "R-FT-TTO-MPC[rtg=value]",
                "horizon": 10,
                "baseline_horizon": 30,
                "runs": 4,
                "feasible": 4,
                "baseline_feasible": 4,
                "vs_baseline": _iv(0.05, 0.02),
                "step_ratio": 3.5,
            },
            {
                "plant": "nominal",
                "method": "REL-MPC",
                "horizon": 10,
                "baseline_horizon": 30,
                "runs": 4,
                "feasible": 4,
                "baseline_feasible": 4,
                "vs_baseline": _iv(0.9),
                "step_ratio": 1.5,
            },
        ],
    }
    evaluation = validate_evaluations(card_metrics("FT-TTO", mpc=report))["mpc"]
    m = evaluation["metrics"]
    assert m["mpc10_nominal_model_rel_increment"] == pytest.approx(0.3)
    assert m["mpc10_nominal_robust_vs_rel30"] == pytest.approx(0.05)
    assert m["mpc10_nominal_robust_vs_rel30_se"] == pytest.approx(0.02)
    assert m["mpc10_nominal_robust_vs_rel30_n"] == 10
    assert m["mpc10_nominal_robust_vs_rel30_step_ratio"] == pytest.approx(3.5)
    assert m["mpc30_nominal_rel_rel_increment"] == pytest.approx(0.2)  # the baseline of the headline
    assert "mpc10_nominal_rel_vs_rel30" not in m and "mpc30_nominal_model_feasible_rate" not in m
    assert evaluation["command"] == report["command"]
    task, keys = headline_metrics(m, "FT-TTO") or ({}, [])
    assert task["type"] == "model-predictive-control" and dict(keys) == {
        "mpc10_nominal_model_feasible_rate": "FT-TTO-MPC@10: goals reached, nominal plant",  # 4/4 goals beat 2/4
        "mpc10_nominal_model_rel_increment": "FT-TTO-MPC@10: (J - J_REL)/J_REL, nominal plant",
        "mpc10_nominal_rel_feasible_rate": "REL-MPC@10: goals reached, nominal plant",
        "mpc10_nominal_rel_rel_increment": "REL-MPC@10: (J - J_REL)/J_REL, nominal plant",
        "mpc30_nominal_rel_feasible_rate": "REL-MPC@30: goals reached, nominal plant",
        "mpc30_nominal_rel_rel_increment": "REL-MPC@30: (J - J_REL)/J_REL, nominal plant",
    }
    tie = {**m, "mpc10_nominal_robust_feasible_rate": 1.0}  # as many goals: the cheaper variant
    assert [k for k, _ in (headline_metrics(tie, "FT-TTO") or ({}, []))[1][:2]] == [
        "mpc10_nominal_robust_feasible_rate",
        "mpc10_nominal_robust_rel_increment",
    ]
    assert headline_metrics({"success_rate": 0.9}, "TTO") is None


def test_ft_metrics_pick_the_ft_rows() -> None:
    m = card_metrics("FT-TTO", warmstart=WS)["warmstart"]["metrics"]
    assert m["ws_suboptimality"] == pytest.approx(0.45)
    assert m["ws_gain_share"] == pytest.approx(-0.5)


def test_missing_method_is_named() -> None:
    with pytest.raises(KeyError, match="FT-TTO-MPC"):
        card_metrics("FT-TTO", mpc=MPC)


def test_a_report_without_its_command_is_one_line_naming_the_fix(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A report written before ``ttompc evaluate`` recorded its ``command`` is refused (the card would print no
    command to reproduce it): a ``UserError``, on the command line one line and exit code 2."""
    from ttompc.cli import main

    old = {k: v for k, v in MPC.items() if k != "command"}
    with pytest.raises(UserError, match=r"closed-loop report \(mpc.json\) records no command"):
        card_metrics("TTO", mpc=old)
    (tmp_path / "mpc.json").write_text(json.dumps(old))
    monkeypatch.delenv("TTOMPC_DEBUG", raising=False)
    assert main(["zoo", "metrics", "--method", "TTO", "--mpc", str(tmp_path / "mpc.json")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("ttompc zoo: error: the closed-loop report (mpc.json) records no command")
    assert line.endswith("; re-run `ttompc evaluate mpc ...` to write a report with its command")


def test_an_incomplete_report_is_refused_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A report without ``complete`` (an interrupted run, an older ttompc) never becomes a card's numbers."""
    from ttompc.cli import main

    (tmp_path / "mpc.json").write_text(json.dumps({k: v for k, v in MPC.items() if k != "complete"}))
    monkeypatch.delenv("TTOMPC_DEBUG", raising=False)
    assert main(["zoo", "metrics", "--method", "TTO", "--mpc", str(tmp_path / "mpc.json")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"{tmp_path / 'mpc.json'} is not a complete report" in line


def test_cli_writes_publishable_metrics(tmp_path) -> None:
    ws = tmp_path / "warmstart.json"
    ws.write_text(json.dumps(WS))
    out = tmp_path / "metrics.json"
    cmd = [sys.executable, "-m", "ttompc.cli", "zoo", "metrics", "--method", "TTO", "--warmstart", str(ws)]
    done = subprocess.run([*cmd, "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    written = validate_evaluations(json.loads(out.read_text()))
    assert list(written) == ["warmstart"] and written["warmstart"]["metrics"]["ws_suboptimality"] == pytest.approx(0.35)
    # the headline as the card shows it, for its body: each value at the precision of its standard error (0.01)
    assert "| warmstart | (J - J_REL)/J_REL, SCP from the TTO warm start | 0.350 ± 0.010 |" in done.stdout
    assert "| warmstart | SCP iterations from the REL warm start | 5.800 ± 0.010 |" in done.stdout
    bad = subprocess.run([*cmd[:-4], "--method", "TTO"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "needs a report" in bad.stderr


def test_an_undefined_gain_share_is_left_off_the_card(tmp_path: Path) -> None:
    """REL, TTO and the oracle at the same cost: no reachable gain to share, so no ws_gain_share (not a number)."""
    import numpy as np

    from ttompc.evaluation.metrics import gain_share, write_json

    cost = np.full(10, 1.123)
    methods = [
        dict(m, gain_share=gain_share(cost + 1e-9, cost, cost)) if m["method"] == "TTO" else m for m in WS["methods"]
    ]
    report = json.loads(write_json(tmp_path / "warmstart.json", {**WS, "methods": methods}).read_text())
    assert report["methods"][1]["gain_share"]["mean"] is None
    m = validate_evaluations(card_metrics("TTO", warmstart=report))["warmstart"]["metrics"]
    assert "ws_gain_share" not in m and m["ws_suboptimality"] == pytest.approx(0.35)


def test_card_inference_names_the_value_rtg_of_a_model_with_a_value_output() -> None:
    from ttompc.zoo.publish import inference_settings

    plain = inference_settings({"model": {"n_embd": 8}, "extra": {"rtg_scale": 1.15}})
    valued = inference_settings({"model": {"n_embd": 8, "value_width": 16}, "extra": {"rtg_scale": 1.15}})
    assert plain == {
        "rtg_scale": 1.15,
        "conditioning": "rtg_0 = -rtg_scale * J_REL (cost of the relaxed problem), ctg_0 = 0",
    }
    assert valued["conditioning"].startswith("rtg_t = -V(x_t, t)") and "rtg_mode=value" in valued["conditioning"]
    assert plain["conditioning"] in valued["conditioning"]  # the ledger it keeps under protocol=paper


@pytest.mark.parametrize(
    ("value", "se", "rounded", "text"),
    [
        (0.837622734441122, 0.153, 0.84, "0.84 ± 0.15"),  # two significant digits of the s.e., the mean to match
        (1049.3, 68.7, 1049.0, "1049 ± 69"),
        (446.9, 152.0, 450.0, "450 ± 150"),  # tens: no exponent notation
        (0.0032651321326674755, 0.000312, 0.00327, "0.00327 ± 0.00031"),
        (-0.004, 0.2, 0.0, "0.00 ± 0.20"),  # no "-0.00"
        (0.8376, None, 0.838, "0.838"),  # no standard error: three significant digits
        (0.9, float("nan"), 0.9, "0.9"),  # nor trailing zeros that claim a precision
        (1049.3, 0.0, 1050.0, "1050"),
    ],
)
def test_numbers_are_rounded_to_what_their_standard_error_supports(
    value: float, se: float | None, rounded: float, text: str
) -> None:
    assert round_to_se(value, se) == rounded
    assert format_with_se(value, se) == text


def test_a_card_shows_each_metric_with_its_standard_error() -> None:
    metrics = {"ws_suboptimality": 0.4327860321807093, "ws_suboptimality_se": 0.02843456346991821, "n": 20}
    assert shown(metrics, "ws_suboptimality") == "0.433 ± 0.028"
    assert shown(metrics, "ws_suboptimality_se") == "0.028"
    assert shown(metrics, "n") == "20"  # a count as it is
