"""Model-card metrics taken from ``ttompc evaluate`` reports, so every number on a card is a report's number and its
``how`` is the command line that produced it (re-run it to check the card).

``card_metrics("TTO", warmstart=..., mpc=...)`` reads the open-loop report (``warmstart.json``) and the closed-loop
report (``mpc.json``) of the evaluation protocol (docs/evaluation.md) and returns ``{name: {value, how}}`` for a
card's front matter (``ttompc zoo publish --card-metrics``, ``ttompc zoo metrics``).
"""

from __future__ import annotations

from typing import Any

from ttompc.zoo.cards import is_metric_value

# config keys that are part of the protocol's command line (others are defaults or output locations)
_WS_KEYS = ("problems", "seed", "nonconvex_only", "rtg_scale", "oracle_detours")
_MPC_KEYS = (
    "problems", "seed", "horizons", "plants", "robust_blend", "rtg_scale", "protocol",
)  # fmt: skip


def command_line(kind: str, config: dict[str, Any]) -> str:
    """The ``ttompc evaluate KIND`` command that reproduces a report with ``config`` (its ``config`` section)."""
    parts = ["ttompc evaluate", kind]
    for flag, key in (("--model", "model"), ("--ft-model", "ft_model")):
        if config.get(key):
            parts.append(f"{flag} {config[key]}")
    for key in _WS_KEYS if kind == "warmstart" else _MPC_KEYS:
        if config.get(key) is not None:  # None: the model's own default (e.g. rtg_scale), nothing to pass
            value = config[key]
            if isinstance(value, list):
                value = "[" + ",".join(str(v) for v in value) + "]"
            parts.append(f"{key}={value}")
    if kind == "mpc":  # the protocol's overridden settings
        parts += [f"mpc.{key}={value}" for key, value in (config.get("mpc") or {}).items()]
    return " ".join(parts)


def _put(out: dict[str, dict[str, Any]], name: str, value: Any, how: str) -> None:
    """Add a metric only when the report has a finite number for it (an undefined mean is not a value)."""
    if is_metric_value(value):
        out[name] = {"value": float(value), "how": how}


def warmstart_metrics(report: dict[str, Any], method: str) -> dict[str, dict[str, Any]]:
    """Open-loop metrics of ``method`` (``TTO`` or ``FT-TTO``) with REL and the oracle ceiling beside it."""
    rows = {r["method"]: r for r in report["methods"]}
    if method not in rows:
        raise KeyError(f"the warm-start report has no method {method!r} (it has {sorted(rows)})")
    cmd = command_line("warmstart", report["config"])
    n = report["config"].get("problems")
    what = f"`{cmd}`: {n} held-out non-convex problems, full-horizon SCP"
    out: dict[str, dict[str, Any]] = {}
    for tag, name in (("", method), ("_rel", "REL"), ("_oracle", "ORACLE")):
        row = rows.get(name)
        if row is None:
            continue
        sub = row["suboptimality"]
        warm = "the best optimum of several warm starts (oracle)" if name == "ORACLE" else f"{name} warm start"
        _put(out, f"ws_suboptimality{tag}", sub["mean"], f"{what} from {warm}: mean (J - J_REL)/J_REL over solved runs")
        _put(out, f"ws_suboptimality{tag}_se", sub["se"], f"{what} from {warm}: standard error of that mean")
        _put(out, f"ws_iterations{tag}", row["iterations"]["mean"], f"{what} from {warm}: mean SCP iterations")
        _put(out, f"ws_failures{tag}", row["failures"], f"{what} from {warm}: SCP runs ending infeasible (of {n})")
    for key, label in (("suboptimality", "suboptimality, (J - J_REL)/J_REL"), ("iterations", "SCP iterations")):
        d = rows[method].get("vs_rel", {}).get(key)
        if d is not None:
            how = f"{what}: paired difference {method} - REL in {label}, on the problems both solved (negative: better)"
            _put(out, f"ws_{key}_vs_rel", d["mean"], how)
            _put(out, f"ws_{key}_vs_rel_se", d["se"], f"{how}: standard error")
    share = rows[method].get("gain_share")
    if share is not None:  # an undefined share (null: the reachable gain is within noise) is no metric
        _put(
            out,
            "ws_gain_share",
            share["mean"],
            f"{what}: share of the oracle-reachable gain over SCP-from-REL captured by the {method} warm start "
            "(1 = the oracle, 0 = REL, negative = worse than REL; undefined when the reachable gain is within noise)",
        )
    return out


def mpc_metrics(report: dict[str, Any], method: str, horizon: int = 10) -> dict[str, dict[str, Any]]:
    """Closed-loop metrics at ``horizon`` of ``method``'s TTO-MPC and robust R-TTO-MPC, with REL-MPC and the oracle,
    per plant (nominal, perturbed)."""
    cmd = command_line("mpc", report["config"])
    n = report["config"].get("problems")
    names = {
        "model": f"{method}-MPC",
        "robust": f"R-{method}-MPC",
        "rel": "REL-MPC",
        "oracle": "ORACLE-MPC",
        "planonce": "PLAN-ONCE",
    }
    tags = {m: t for t, m in names.items()}  # a report's method (without its rtg label) -> the metric's tag
    if names["model"] not in {base_method(r["method"]) for r in report["summary"]}:
        raise KeyError(f"the closed-loop report has no method {names['model']!r}")
    out: dict[str, dict[str, Any]] = {}
    for row in report["summary"]:
        tag = tags.get(base_method(row["method"]))
        if tag is None or row["horizon"] != horizon:
            continue
        what = f"`{cmd}`: {n} held-out non-convex problems, {row['plant']} plant, {row['method']} at H={horizon}"
        key = f"mpc{horizon}_{row['plant']}_{tag}"
        _put(out, f"{key}_feasible_rate", row["feasible"] / row["runs"], f"{what}: share of episodes feasible")
        _put(
            out,
            f"{key}_rel_increment",
            row["rel_increment"]["mean"],
            f"{what}: mean (J - J_REL)/J_REL over its feasible episodes",
        )
        if "paper_norm" in row:
            _put(
                out,
                f"{key}_paper_norm",
                row["paper_norm"]["mean"],
                f"{what}: paper normalisation (problems feasible for every method, DIST-MPC = 1)",
            )
        vs = row.get("vs_rel_mpc")  # every method but REL-MPC itself
        if vs and vs["n"]:
            both = f"on the {vs['n']} problems both ran feasibly"
            how = f"{what}: paired difference to REL-MPC in (J - J_REL)/J_REL {both}"
            _put(out, f"{key}_vs_rel_mpc", vs["mean"], f"{how}, mean (negative: cheaper)")
            _put(out, f"{key}_vs_rel_mpc_se", vs["se"], f"{how}, standard error of the mean (negative: cheaper)")
        _put(out, f"{key}_step_time_s", row["mean_step_time"], f"{what}: mean MPC step time [s], shared 2-core CPU")
    for row in report.get("headline", []):  # the paper's headline: against REL-MPC at the longest horizon
        tag = tags.get(base_method(row["method"]))
        if tag is None or tag == "rel" or row["horizon"] != horizon:
            continue
        long = row["baseline_horizon"]
        what = (
            f"`{cmd}`: {n} held-out non-convex problems, {row['plant']} plant, {row['method']} at H={horizon} against "
            f"REL-MPC at H={long}"
        )
        key = f"mpc{horizon}_{row['plant']}_{tag}_vs_rel{long}"
        vs = row["vs_baseline"]
        if vs["n"]:
            how = f"{what}: paired difference in (J - J_REL)/J_REL on the {vs['n']} problems both ran feasibly"
            _put(out, key, vs["mean"], f"{how}, mean (negative: cheaper)")
            _put(out, f"{key}_se", vs["se"], f"{how}, standard error of the mean")
        _put(out, f"{key}_step_ratio", row["step_ratio"], f"{what}: REL-MPC's mean step time over this method's")
    return out


def base_method(name: str) -> str:
    """A report's method name without its rtg-mode label: ``FT-TTO-MPC[rtg=value]`` -> ``FT-TTO-MPC``."""
    return name.split("[", 1)[0]


def card_metrics(
    method: str, *, warmstart: dict[str, Any] | None = None, mpc: dict[str, Any] | None = None, horizon: int = 10
) -> dict[str, dict[str, Any]]:
    """All card metrics of ``method`` from the given reports (either may be missing)."""
    out: dict[str, dict[str, Any]] = {}
    if warmstart is not None:
        out.update(warmstart_metrics(warmstart, method))
    if mpc is not None:
        out.update(mpc_metrics(mpc, method, horizon))
    return out
