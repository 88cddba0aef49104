"""Model-card evaluations taken from ``ttompc evaluate`` reports, so every number on a card is a report's number and
its evaluation's ``command`` is the command line that produced it, as the report records it (re-run it to check the
card).

``card_metrics("TTO", warmstart=..., mpc=...)`` reads the open-loop report (``warmstart.json``) and the closed-loop
report (``mpc.json``) of the evaluation protocol (docs/evaluation.md) and returns the card's evaluations
``{"warmstart": {command, what, metrics}, "mpc": {...}}`` (``ttompc zoo metrics``, ``ttompc zoo publish
--card-metrics``: the card's metrics file). Every mean comes with its standard error (``<key>_se``), which sets the
precision the card shows it at (``ttompc.zoo.rounding``). The metric keys are defined in zoo/README.md.
"""

from __future__ import annotations

from typing import Any

from ttompc.errors import UserError
from ttompc.evaluation.warmstart import BASELINE as WS_BASELINE
from ttompc.evaluation.warmstart import ORACLE
from ttompc.mpc.methods import METHODS, base_method, model_method
from ttompc.zoo.evaluations import is_metric_value

_REPORTS = {"warmstart": "warm-start", "mpc": "closed-loop"}  # a report's kind -> its name in messages


def recorded_command(report: dict[str, Any], kind: str) -> str:
    """The ``command`` a ``ttompc evaluate KIND`` report records (the line that reproduces it); raises
    ``UserError`` (one line, what to do) for a report without one (written by a ttompc before reports recorded
    it)."""
    command = report.get("command")
    if not isinstance(command, str) or not command:
        raise UserError(
            f"the {_REPORTS[kind]} report ({kind}.json) records no command (it was written by an older ttompc)",
            f"re-run `ttompc evaluate {kind} ...` to write a report with its command",
        )
    return command


def _put(out: dict[str, float], name: str, value: Any) -> None:
    """Add a metric only when the report has a finite number for it (an undefined mean is not a value)."""
    if is_metric_value(value):
        out[name] = float(value)


def _put_mean(out: dict[str, float], name: str, interval: dict[str, Any]) -> None:
    """A mean (``name``) and its standard error (``name_se``), each when the report has a finite number for it."""
    _put(out, name, interval["mean"])
    _put(out, f"{name}_se", interval.get("se"))


def _put_paired(out: dict[str, float], name: str, interval: dict[str, Any]) -> None:
    """A paired difference: its mean (``name``), standard error (``name_se``) and how many problems it pairs
    (``name_n``)."""
    _put_mean(out, name, interval)
    out[f"{name}_n"] = int(interval["n"])


def warmstart_metrics(report: dict[str, Any], method: str) -> dict[str, float]:
    """Open-loop metrics of ``method`` (``TTO`` or ``FT-TTO``) with REL and the oracle ceiling beside it."""
    rows = {r["method"]: r for r in report["methods"]}
    if method not in rows:
        raise KeyError(f"the warm-start report has no method {method!r} (it has {sorted(rows)})")
    out: dict[str, float] = {}
    for tag, name in (("", method), ("_rel", WS_BASELINE), ("_oracle", ORACLE)):
        row = rows.get(name)
        if row is None:
            continue
        _put_mean(out, f"ws_suboptimality{tag}", row["suboptimality"])
        _put_mean(out, f"ws_iterations{tag}", row["iterations"])
        _put(out, f"ws_failures{tag}", row["failures"])
    for key in ("suboptimality", "iterations"):
        d = rows[method].get("vs_rel", {}).get(key)
        if d is not None and d["n"]:
            _put_paired(out, f"ws_{key}_vs_rel", d)
    share = rows[method].get("gain_share")
    if share is not None:  # an undefined share (null: the reachable gain is within noise) is no metric
        _put_mean(out, "ws_gain_share", share)
    return out


def mpc_metrics(report: dict[str, Any], method: str, horizon: int = 10) -> dict[str, float]:
    """Closed-loop metrics at ``horizon`` of the model slot ``method``'s methods (TTO-MPC and robust R-TTO-MPC for
    "TTO") and of the methods without a model that have a card tag (``Method.tag``: REL-MPC, the oracle and
    plan-once), per plant (nominal, perturbed); with the paper's headline (the methods against REL-MPC at the longest
    horizon) REL-MPC's metrics at that horizon too."""
    tags = {m.name: m.tag for m in METHODS.values() if m.tag and m.model in (None, method)}  # report name -> tag
    model = model_method(method).name
    if model not in {base_method(r["method"]) for r in report["summary"]}:
        raise KeyError(f"the closed-loop report has no method {model!r}")
    headline = [r for r in report.get("headline", []) if r["horizon"] == horizon]
    baseline_horizons = {r["baseline_horizon"] for r in headline}
    out: dict[str, float] = {}
    for row in report["summary"]:
        tag = tags.get(base_method(row["method"]))
        if tag is None or not (row["horizon"] == horizon or (tag == "rel" and row["horizon"] in baseline_horizons)):
            continue
        key = f"mpc{row['horizon']}_{row['plant']}_{tag}"
        _put(out, f"{key}_feasible_rate", row["feasible"] / row["runs"])
        _put_mean(out, f"{key}_rel_increment", row["rel_increment"])
        if "paper_norm" in row:
            _put_mean(out, f"{key}_paper_norm", row["paper_norm"])
        vs = row.get("vs_rel_mpc")  # every method but REL-MPC itself
        if vs and vs["n"]:
            _put_paired(out, f"{key}_vs_rel_mpc", vs)
        _put(out, f"{key}_step_time_s", row["mean_step_time"])
    for row in headline:  # the paper's headline: against REL-MPC at the longest horizon
        tag = tags.get(base_method(row["method"]))
        if tag is None or tag == "rel":
            continue
        key = f"mpc{horizon}_{row['plant']}_{tag}_vs_rel{row['baseline_horizon']}"
        if row["vs_baseline"]["n"]:
            _put_paired(out, key, row["vs_baseline"])
        _put(out, f"{key}_step_ratio", row["step_ratio"])
    return out


def card_metrics(
    method: str, *, warmstart: dict[str, Any] | None = None, mpc: dict[str, Any] | None = None, horizon: int = 10
) -> dict[str, dict[str, Any]]:
    """The card's evaluations of ``method`` from the given reports (either may be missing): ``warmstart`` and
    ``mpc``, each ``{command, what, metrics}`` with the command that reproduces the report (``recorded_command``:
    a report without one is a ``UserError``)."""
    out: dict[str, dict[str, Any]] = {}
    if warmstart is not None:
        config = warmstart["config"]
        out["warmstart"] = {
            "command": recorded_command(warmstart, "warmstart"),
            "what": f"{config.get('problems')} held-out non-convex problems, full-horizon SCP from the {method}, REL "
            "and oracle warm starts",
            "metrics": warmstart_metrics(warmstart, method),
        }
    if mpc is not None:
        config = mpc["config"]
        plants = config.get("plants") or ["nominal"]
        out["mpc"] = {
            "command": recorded_command(mpc, "mpc"),
            "what": f"{config.get('problems')} held-out non-convex problems, closed-loop MPC on the "
            f"{' and '.join(plants)} plant{'s' if len(plants) > 1 else ''}",
            "metrics": mpc_metrics(mpc, method, horizon),
        }
    return out
