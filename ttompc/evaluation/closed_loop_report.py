"""The report of the closed-loop study (``ttompc evaluate mpc``, ``ttompc.evaluation.closed_loop``): its rows, tables
and the files it writes.

Reported per (plant, method, H): runs, feasible and infeasible counts (infeasible or goal-missing runs are never
averaged into a cost: their rate is shown), (J − J_REL)/J_REL over feasible runs with standard error and bootstrap
interval, the paper's normalised cost increment (``metrics.normalized_cost``: per problem, its worst feasible run
= 1), the paired difference to REL-MPC on the problems both ran feasibly (fair where the feasible sets differ), the
share of the reachable gain REL-MPC → ORACLE-MPC, plan consistency (mean change of the terminal target between
steps), step times and SCP iterations per solved step (``summarize``, ``format_table``); with more than one horizon,
every method at the shortest against REL-MPC at the longest (``headline``) and the speedup at equal cost
(``ttompc.evaluation.equal_cost``). The report names its protocol (``protocol_label``) and
records the resolved settings and the command line that reproduces it (``command``,
``ttompc.evaluation.reproduce``); the settings that depart from the paper preset (``ttompc.mpc.departures``)
are listed under the table (``write_report``). Every paired difference is ``stats.paired``'s.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.evaluation.episodes import summarize_episodes
from ttompc.evaluation.equal_cost import equal_cost, format_equal_cost
from ttompc.evaluation.machine import load_average, machine_record
from ttompc.evaluation.measurement import Measurement
from ttompc.evaluation.metrics import format_gain_share, gain_share, normalized_cost, write_csv
from ttompc.evaluation.report_files import finish, retract
from ttompc.evaluation.reproduce import report_command
from ttompc.evaluation.stats import Outcome, format_interval, paired
from ttompc.mpc.departures import departures
from ttompc.mpc.methods import BASELINE, CEILING
from ttompc.scenarios.base import Scenario
from ttompc.solvers.backends import solver_path


def protocol_label(cfg: Measurement) -> str:
    """How a report names its protocol: the preset, and the overrides when there are any."""
    overrides = " ".join(f"mpc.{k}={v}" for k, v in cfg.mpc.items())
    return f"{cfg.protocol} {overrides}" if overrides else cfg.protocol


def summarize(records: list[dict[str, Any]], seed: int = 0) -> list[dict[str, Any]]:
    """Rows per (plant, method, horizon): ``summarize_episodes`` + the paper's normalised cost increment
    (``paper_norm``) + share of reachable gain."""
    rows = []
    for plant in sorted({r["plant"] for r in records}):
        recs = [r for r in records if r["plant"] == plant]
        methods = list(dict.fromkeys(r["method"] for r in recs))
        paper = {(p["method"], p["horizon"]): p["paper_norm"] for p in normalized_cost(recs, seed=seed)}
        for m in methods:
            for H in sorted({r["horizon"] for r in recs}):
                group = [r for r in recs if r["method"] == m and r["horizon"] == H]
                row: dict[str, Any] = {
                    "plant": plant,
                    "method": m,
                    "horizon": H,
                    **summarize_episodes(group, seed=seed),
                }
                if (m, H) in paper:
                    row["paper_norm"] = paper[(m, H)]
                if m != BASELINE:  # paired with REL-MPC on the problems both ran feasibly
                    runs = {
                        k: {r["problem"]: Outcome.of(r) for r in recs if r["method"] == k and r["horizon"] == H}
                        for k in (BASELINE, m)
                    }
                    row["vs_rel_mpc"] = paired(runs[BASELINE], runs[m], seed=seed)["paired"]
                if m not in (BASELINE, CEILING):
                    cost = {
                        k: {
                            r["problem"]: (r["cost"] if r["feasible"] else np.nan)
                            for r in recs
                            if r["method"] == k and r["horizon"] == H
                        }
                        for k in (BASELINE, m, CEILING)
                    }
                    probs = sorted(cost[m])
                    row["gain_share"] = gain_share(
                        *(np.array([cost[k].get(p, np.nan) for p in probs]) for k in (BASELINE, m, CEILING)), seed=seed
                    )
                rows.append(row)
    return rows


def headline(records: list[dict[str, Any]], seed: int = 0) -> list[dict[str, Any]]:
    """The paper's headline comparison, when more than one horizon ran: every method at the shortest horizon against
    REL-MPC at the longest, per plant: goals reached, the paired difference in (J − J_REL)/J_REL over the problems
    both reach feasibly, and how many times lower the mean step time is. Empty for a single horizon."""
    horizons = sorted({r["horizon"] for r in records})
    if len(horizons) < 2:
        return []
    short, long = horizons[0], horizons[-1]
    rows = []
    for plant in sorted({r["plant"] for r in records}):
        base = [r for r in records if r["plant"] == plant and r["method"] == BASELINE and r["horizon"] == long]
        ref = {r["problem"]: Outcome.of(r) for r in base}
        for m in dict.fromkeys(r["method"] for r in records if r["plant"] == plant):
            group = [r for r in records if r["plant"] == plant and r["method"] == m and r["horizon"] == short]
            pair = paired(ref, {r["problem"]: Outcome.of(r) for r in group}, seed=seed)
            rows.append(
                {
                    "plant": plant,
                    "method": m,
                    "horizon": short,
                    "baseline_horizon": long,
                    "runs": len(group),
                    "feasible": sum(r["feasible"] for r in group),
                    "baseline_feasible": sum(r["feasible"] for r in base),
                    "vs_baseline": pair["paired"],
                    "step_ratio": pair["step_ratio"],
                }
            )
    return rows


def format_headline(rows: list[dict[str, Any]]) -> str:
    """A markdown table of ``headline`` (empty string when there is none)."""
    if not rows:
        return ""
    H, long = rows[0]["horizon"], rows[0]["baseline_horizon"]
    lines = [
        f"\n### Against {BASELINE}@{long}: every method at H = {H}\n",
        f"| plant | method | goals | {BASELINE}@{long} goals | paired vs {BASELINE}@{long}, points (n) "
        f"| step time vs {BASELINE}@{long} |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        vs = r["vs_baseline"]
        paired = f"{format_interval(vs, 100)} ({vs['n']})" if vs["n"] else "–"
        lines.append(
            f"| {r['plant']} | {r['method']} | {r['feasible']}/{r['runs']} | {r['baseline_feasible']}/{r['runs']} "
            f"| {paired} | {r['step_ratio']:.1f}× lower |"
        )
    return "\n".join(lines)


def format_table(summary: list[dict[str, Any]]) -> str:
    """A readable markdown table of ``summarize``."""
    lines = [
        "| plant | method | H | feasible (failed) | (J − J_REL)/J_REL, % (mean ± s.e. [95% CI]) | paired vs REL-MPC, "
        "points (n) | (J − LB)/(maxcost − LB) | share of reachable gain, % | goal miss of infeasible runs [m] "
        "| target change "
        "| mean / max step [ms] | SCP it. / solved step |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in summary:
        paper = format_interval(r["paper_norm"], 1, 2) if "paper_norm" in r else "–"
        share = format_gain_share(r["gain_share"]) if "gain_share" in r else "–"
        vs = r.get("vs_rel_mpc")
        paired = f"{format_interval(vs, 100)} ({vs['n']})" if vs and vs["n"] else "–"
        failed = 100 * (1 - r["feasible"] / r["runs"]) if r["runs"] else float("nan")
        lines.append(
            f"| {r['plant']} | {r['method']} | {r['horizon']} | {r['feasible']}/{r['runs']} ({failed:.0f}%) "
            f"| {format_interval(r['rel_increment'], 100)} | {paired} | {paper} | {share} "
            f"| {format_interval(r['infeasible_terminal_error'], 1, 2)} | {r['target_change']['mean']:.3g} "
            f"| {r['mean_step_time'] * 1e3:.3g} / {r['max_step_time'] * 1e3:.3g} "
            f"| {r['mean_iterations_solved']:.2f} |"
        )
    lines.append(
        "\nCosts average feasible runs only; infeasible runs (keep-out, path or goal tolerance violated) are counted "
        "in 'feasible' (failed: their rate) and described by their goal miss. (J − LB)/(maxcost − LB): the paper's "
        "normalised cost increment per feasible run, LB = J_REL of its problem and maxcost the problem's worst "
        "feasible cost over every method and H of the plant (= 1). Paired vs REL-MPC: the mean per-problem "
        "difference in "
        "(J − J_REL)/J_REL over the n problems both ran feasibly (negative: cheaper). Share of reachable gain: "
        "REL-MPC = 0, ORACLE-MPC = 100; "
        "undefined when the reachable gain (REL-MPC − ORACLE-MPC cost) is within noise. A step: observing the "
        "previous step's outcome (TTO: the KV-cache advance) + warm start + window SCP, each run charged its share of "
        "batched work; SCP iterations: per step that solved its window (plan reuse excluded)."
    )
    cut = sum(r["truncated"] for r in summary)
    if cut:
        lines.append(
            f"Truncated: {cut} of {sum(r['runs'] for r in summary)} runs stopped at max_steps before step N (a smoke "
            "run): they reach no goal, so they count as failed and have no cost."
        )
    return "\n".join(lines)


def write_report(
    cfg: Measurement,
    sc: Scenario,
    records: list[dict[str, Any]],
    out: Path,
    workers: int,
    started: float,
    load_start: list[float] | None = None,
) -> dict[str, Any]:
    """The report of the episode ``records`` of the measurement ``cfg`` (a ``ClosedLoopConfig``) on ``sc``: writes
    ``mpc.md`` (the table), ``mpc_runs.csv``, plots and last ``mpc.json`` (marked complete, ``report_files.finish``)
    into ``out`` and returns the report; ``workers`` is recorded in its config, the config's ``report_command`` as
    its ``command``, ``started`` (``time.perf_counter()`` at the start) gives its wall time (this run's, when a sweep
    resumed) and ``load_start`` (``machine.load_average()`` then; default now) its ``machine``."""
    from ttompc.evaluation.plots import plot_horizon

    summary = summarize(records, cfg.seed)
    settings = cfg.settings
    notes = departures(settings, sc)
    head = headline(records, cfg.seed)
    table = format_table(summary) + f"\nProtocol: {protocol_label(cfg)}."
    if notes:
        table += "\nDepartures from the paper: " + "; ".join(notes) + "."
    table += format_headline(head)
    matches = equal_cost(records, seed=cfg.seed) if len(cfg.horizons) > 1 else []
    table += format_equal_cost(matches)
    config = {**asdict(cfg), "out": str(out), "workers": workers}
    report = {
        "config": config,
        "command": report_command("mpc", config, type(cfg)()),  # the line that reproduces the report (``reproduce``)
        "protocol": {"name": protocol_label(cfg), "settings": asdict(settings)},
        "solver": solver_path(settings.backend, sc),
        "scenario": {"name": sc.name, "version": sc.version, "n_steps": sc.n_steps},
        "perturbed_plant": asdict(cfg.plant.resolve(sc)),  # the disturbance the perturbed episodes met
        "wall_time_s": time.perf_counter() - started,
        "machine": machine_record(load_start or load_average()),  # what the step times ran on
        "departures": notes,
        "summary": summary,
        "headline": head,
        "equal_cost": matches,
        "table": table,
        "runs": records,
    }
    out.mkdir(parents=True, exist_ok=True)
    retract(out / "mpc.json")
    (out / "mpc.md").write_text(f"# Closed loop: {sc.name}, {cfg.problems} problems\n\n{table}\n")
    write_csv(out / "mpc_runs.csv", records)
    report["plots"] = [str(p) for p in plot_horizon(summary, out)]
    finish(out / "mpc.json", report)
    report["out"] = str(out)
    return report
