"""SCP engine speed and robustness, measured against baselines and a peer in the same run.

1. Peer (free-flyer, quadrotor; the same seeded problems, interleaved): REL + SCP with the PIQP path ("ours",
   ``backend="piqp"``: PIQP on the compact QP, ∞-norm trust region; ``auto`` without the kernel), the Riccati
   interior-point backend (``backend="riccati"``, the default ``auto``), the conic path (``backend="conic"``:
   QOCO/Clarabel, 2-norm trust region; the default before the QP path), and IPOPT and fatrop through CasADi, each
   built once as parametric NLPs with ``expand=True`` (REL, then the full problem from the REL solution;
   ``bench/ipopt_peer.py``, ``bench/fatrop_peer.py``, the ``peer`` extra). Median wall and CPU time per problem,
   iterations (SCP subproblems / NLP iterations), failures, costs relative to IPOPT's and ours; fatrop's time per
   iteration split into its Riccati search direction and CasADi's function evaluations.
2. Robustness (free-flyer and quadrotor, 200 seeded problems each): failures of the PIQP path and of the Riccati
   backend (the default); for the free-flyer also the reference formulation (hard linearised constraints, on its own
   path: Clarabel) and its costs where both succeed.
3. Subproblems (free-flyer, quadrotor; ``--only subproblems``): every subproblem of REL + SCP on a few seeded
   problems, recorded from the PIQP path and re-solved in the same order by PIQP (as the engine calls it: one
   solver per structure, updated in place, restarted per solve) and by the Riccati backend, problem by problem in
   alternating order, the least of 3 repeats: CPU-ms per subproblem, interior-point iterations, the largest
   objective difference.
4. Engine (free-flyer, quadrotor; ``--only engine``): REL + SCP with the Riccati backend's per-iteration Python around
   the kernel as the NumPy reference (``RiccatiSolver.compiled = False``) and compiled (``riccati_build``, the
   default), the same seeded problems, interleaved: median CPU ms per problem and the ratio, whether both paths give
   the same statuses and iterates (largest |ΔX|), interior-point iterations per subproblem, the kernel's distance
   from its arithmetic (CPU time per interior-point iteration against its flops, ``engine_limit.kernel_flops``),
   MPC windows (H = 10, 30) cut from the solutions, by both paths, and the kernel's warm start between SCP
   iterations against cold starts: interior-point iterations, costs, statuses (``bench/engine_paths.py``).
5. Naive baseline (every scenario, a few problems): time per SCP iteration of the default (``auto``) vs rebuilding a
   cvxpy problem from per-timestep constraint lists every iteration (the reference's approach), and the cost
   difference.

Ends with one JSON line of headline figures, also written to bench/results/solver_speed.json.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from record import Machine, read_result, result_path, write_result

from ttompc.scenarios import get_scenario, list_scenarios
from ttompc.solvers import solve_problem
from ttompc.solvers.backends import backend_chain

PEER_SCENARIOS = ("freeflyer", "quadrotor")


def run_set(scenario, seeds, **kw) -> dict:
    tot, its, solver, costs, ok = [], [], [], [], []
    for seed in seeds:
        p = scenario.sample(np.random.default_rng(seed))
        t0 = time.perf_counter()
        rel, scp = solve_problem(scenario, p, **kw)
        tot.append(time.perf_counter() - t0)
        its.append(rel.iterations + (scp.iterations if scp else 0))
        solver.append(rel.solver_time + (scp.solver_time if scp else 0.0))
        costs.append(scp.cost if scp is not None and scp.success else np.nan)
        ok.append(bool(scp is not None and scp.success))
    tot, its, solver = np.array(tot), np.array(its), np.array(solver)
    return {
        "per_iter_s": float(tot.sum() / its.sum()),
        "solve_median_s": float(np.median(tot)),
        "solve_mean_s": float(tot.mean()),
        "raw_solver_per_iter_s": float(solver.sum() / its.sum()),
        "mean_iterations": float(its.mean()),
        "success_rate": float(np.mean(ok)),
        "costs": costs,
    }


def speed(name: str, n_problems: int, n_naive: int) -> dict:
    scenario = get_scenario(name)
    seeds = list(range(n_problems))
    run_set(scenario, seeds[:1])  # warm the structure cache and imports outside the timing
    ours = run_set(scenario, seeds)
    naive = run_set(scenario, seeds[:n_naive], backend="cvxpy-naive")  # the same subproblems (same trust-region norm)
    c_ours, c_naive = np.array(ours.pop("costs")[:n_naive]), np.array(naive.pop("costs"))
    both = np.isfinite(c_ours) & np.isfinite(c_naive)
    rel_diff = float(np.max(np.abs(c_ours[both] - c_naive[both]) / np.abs(c_naive[both]))) if both.any() else None
    row = {
        "scenario": name,
        "backend": "+".join(backend_chain("auto", scenario)),
        "ours": ours,
        "naive": naive,
        "speedup_per_iter": naive["per_iter_s"] / ours["per_iter_s"],
        "overhead_vs_raw_solver": ours["per_iter_s"] / ours["raw_solver_per_iter_s"],
        "max_rel_cost_diff": rel_diff,
    }
    print(
        f"[{name}] ours {ours['per_iter_s'] * 1e3:.1f} ms/iter (raw solver {ours['raw_solver_per_iter_s'] * 1e3:.1f}"
        f" ms, x{row['overhead_vs_raw_solver']:.2f}), solve median {ours['solve_median_s']:.3f} s | naive "
        f"{naive['per_iter_s'] * 1e3:.0f} ms/iter, solve {naive['solve_mean_s']:.2f} s | speed-up "
        f"x{row['speedup_per_iter']:.1f} | max rel cost diff {rel_diff}",
        flush=True,
    )
    return row


def robustness(name: str, n: int, reference: bool, backend: str) -> dict:
    """Failures of the penalized formulation with ``backend`` on seeds 0..n−1; with ``reference`` also the
    hard-constraint formulation (on its default path, Clarabel) and the costs where both succeed."""
    scenario = get_scenario(name)
    out: dict = {}
    for form in ("penalized", "reference") if reference else ("penalized",):
        costs, fails, its = [], [], []
        for seed in range(n):
            p = scenario.sample(np.random.default_rng(seed))
            rel, scp = solve_problem(scenario, p, formulation=form, backend=backend if form == "penalized" else "auto")
            good = scp is not None and scp.success
            costs.append(scp.cost if good else np.nan)
            its.append(rel.iterations + (scp.iterations if scp else 0))
            if not good:
                fails.append(seed)
        out[form] = {
            "failures": len(fails),
            "failure_rate": len(fails) / n,
            "failed_seeds": fails,
            "mean_iterations": float(np.mean(its)),
            "costs": np.array(costs),
        }
    a = out["penalized"].pop("costs")
    msg = f"[robustness, {name}, {backend}, {n} problems] failures: penalized {out['penalized']['failures']}"
    if reference:
        b = out["reference"].pop("costs")
        both = np.isfinite(a) & np.isfinite(b)
        out["both_succeed"] = int(both.sum())
        out["max_rel_cost_excess_vs_reference"] = float(np.max((a[both] - b[both]) / b[both])) if both.any() else None
        msg += (
            f", reference {out['reference']['failures']}; where both succeed ({out['both_succeed']}) max relative "
            f"cost excess of penalized over reference {out['max_rel_cost_excess_vs_reference']}"
        )
    print(msg, flush=True)
    return out


def peer(name: str, n: int) -> dict:
    """Ours (the PIQP path), the Riccati backend (the default), the conic path, built-once IPOPT and built-once fatrop
    on the same problems, interleaved; wall and CPU time of this process per problem, and the interior-point
    iterations of the Riccati kernel (over all subproblems), IPOPT and fatrop."""

    from fatrop_peer import FatropPeer
    from ipopt_peer import IpoptPeer

    from ttompc.solvers.backends.riccati import RiccatiSolver, status_iterations

    scenario = get_scenario(name)
    ipopt, fatrop = IpoptPeer(scenario), FatropPeer(scenario)
    runners = {
        "ours": lambda p: _ours(scenario, p, "piqp"),
        "conic": lambda p: _ours(scenario, p, "conic"),
        "ipopt": lambda p: _nlp_peer(ipopt, scenario, p),
        "riccati": lambda p: _ours(scenario, p, "riccati"),
        "fatrop": lambda p: _nlp_peer(fatrop, scenario, p),
    }
    warm = scenario.sample(np.random.default_rng(10_000))
    for run in runners.values():  # imports, structure caches, CasADi code generation outside the timing
        run(warm)
    fatrop.profile.clear()
    kernel_its: list[int] = []  # interior-point iterations of each Riccati subproblem solve
    original = RiccatiSolver.solve

    def counted(self, data):
        result = original(self, data)
        kernel_its.append(status_iterations(result[2].status))
        return result

    rows: dict[str, list[tuple[float, float, int, float, bool, int]]] = {k: [] for k in runners}
    order = list(runners)
    RiccatiSolver.solve = counted  # type: ignore[method-assign]
    try:
        for i in range(n):
            p = scenario.sample(np.random.default_rng(i))
            for k in order[i % len(order) :] + order[: i % len(order)]:  # rotate who goes first
                kernel_its.clear()
                w0, c0 = time.perf_counter(), time.process_time()
                its, c, ok = runners[k](p)
                wall, cpu = time.perf_counter() - w0, time.process_time() - c0
                rows[k].append((wall, cpu, its, c, ok, sum(kernel_its) if k == "riccati" else its))
    finally:
        RiccatiSolver.solve = original  # type: ignore[method-assign]
    out: dict = {"scenario": name, "problems": n, "backend": "+".join(backend_chain("piqp", scenario))}
    cost, cpu_time = {}, {}
    for k, r in rows.items():
        t, cpu, its, c, ok, ip_its = (np.array(v) for v in zip(*r, strict=True))
        cost[k], cpu_time[k] = np.where(ok, c, np.nan), cpu
        out[k] = {
            "median_s": float(np.median(t)),
            "mean_s": float(t.mean()),
            "median_cpu_s": float(np.median(cpu)),
            "mean_iterations": float(its.mean()),
            "failures": int((~ok).sum()),
        }
        if k in ("riccati", "ipopt", "fatrop"):  # interior-point iterations per problem, CPU time per iteration
            out[k]["mean_ip_iterations"] = float(ip_its.mean())
            out[k]["cpu_us_per_ip_iteration"] = float(1e6 * cpu.sum() / ip_its.sum())
    out["speedup_vs_ipopt"] = out["ipopt"]["median_s"] / out["ours"]["median_s"]
    out["speedup_vs_conic"] = out["conic"]["median_s"] / out["ours"]["median_s"]
    out["cost_vs_ipopt"] = _cost_vs(cost["ours"], cost["ipopt"])
    out["riccati_speedup_vs_ipopt"] = out["ipopt"]["median_s"] / out["riccati"]["median_s"]
    out["riccati_speedup_vs_ours"] = out["ours"]["median_s"] / out["riccati"]["median_s"]
    out["riccati_cost_vs_ipopt"] = _cost_vs(cost["riccati"], cost["ipopt"])
    out["riccati_cost_vs_ours"] = _cost_vs(cost["riccati"], cost["ours"])
    out["riccati_speedup_vs_fatrop"] = out["fatrop"]["median_s"] / out["riccati"]["median_s"]
    out["riccati_cpu_speedup_vs_fatrop"] = out["fatrop"]["median_cpu_s"] / out["riccati"]["median_cpu_s"]
    out["fatrop_speedup_vs_ipopt"] = out["ipopt"]["median_s"] / out["fatrop"]["median_s"]
    out["fatrop_cost_vs_riccati"] = _cost_vs(cost["fatrop"], cost["riccati"])
    out["fatrop_cost_vs_ipopt"] = _cost_vs(cost["fatrop"], cost["ipopt"])
    ratio = cpu_time["fatrop"] / cpu_time["riccati"]  # per problem, CPU time: < 1 where fatrop is faster
    out["fatrop_faster_problems"] = int(np.sum(ratio < 1))
    out["riccati_cpu_speedup_vs_fatrop_range"] = (float(ratio.min()), float(ratio.max()))
    out["closest_to_fatrop"] = [  # the 3 problems where fatrop comes nearest: seed, CPU ratio, our subproblems
        {"seed": int(i), "cpu_ratio": float(ratio[i]), "subproblems": rows["riccati"][i][2]}
        for i in np.argsort(ratio)[:3]
    ]
    out["fatrop_profile"] = fatrop.profile_per_iteration()
    conic_both = np.isfinite(cost["ours"]) & np.isfinite(cost["conic"])
    out["max_rel_cost_diff_vs_conic"] = float(
        np.max(np.abs(cost["ours"][conic_both] - cost["conic"][conic_both]) / cost["conic"][conic_both])
    )
    print(
        f"[peer {name}, {n} problems] median per problem: ours {out['ours']['median_s'] * 1e3:.1f} ms "
        f"({out['ours']['mean_iterations']:.1f} SCP it.), conic {out['conic']['median_s'] * 1e3:.1f} ms, IPOPT "
        f"{out['ipopt']['median_s'] * 1e3:.1f} ms ({out['ipopt']['mean_iterations']:.1f} it.) | x"
        f"{out['speedup_vs_ipopt']:.2f} vs IPOPT, x{out['speedup_vs_conic']:.2f} vs conic | cost vs IPOPT median "
        f"{out['cost_vs_ipopt']['median_rel_diff']:.1e}",
        flush=True,
    )
    print(
        f"[peer {name}] riccati {out['riccati']['median_s'] * 1e3:.1f} ms ({out['riccati']['mean_iterations']:.1f}"
        f" SCP it.) | x{out['riccati_speedup_vs_ipopt']:.2f} vs IPOPT, x{out['riccati_speedup_vs_ours']:.2f} vs "
        f"ours | cost vs ours median {out['riccati_cost_vs_ours']['median_rel_diff']:.1e}",
        flush=True,
    )
    print(
        f"[peer {name}] fatrop {out['fatrop']['median_s'] * 1e3:.1f} ms ({out['fatrop']['mean_iterations']:.1f} it., "
        f"{out['fatrop']['failures']} failures) | riccati x{out['riccati_speedup_vs_fatrop']:.2f} vs fatrop (CPU x"
        f"{out['riccati_cpu_speedup_vs_fatrop']:.2f}; fatrop faster on {out['fatrop_faster_problems']} of {n}), fatrop "
        f"x{out['fatrop_speedup_vs_ipopt']:.2f} vs IPOPT | cost vs riccati median "
        f"{out['fatrop_cost_vs_riccati']['median_rel_diff']:.1e}",
        flush=True,
    )
    print(
        f"[peer {name}] interior-point iterations per problem (CPU us each): "
        + ", ".join(
            f"{k} {out[k]['mean_ip_iterations']:.0f} ({out[k]['cpu_us_per_ip_iteration']:.0f})"
            for k in ("riccati", "ipopt", "fatrop")
        ),
        flush=True,
    )
    return out


def subproblems(name: str, n: int) -> dict:
    """PIQP and the Riccati backend on the same recorded subproblems, in the order the engine solves them."""

    from ttompc.solvers.backends import qp as qp_module
    from ttompc.solvers.backends.riccati import RiccatiSolver, status_iterations

    scenario = get_scenario(name)
    recorded: list = []
    original = qp_module.PIQPSolver.solve

    def record(self, data):
        recorded[-1].append((self.qp.spec, data))
        return original(self, data)

    qp_module.PIQPSolver.solve = record  # type: ignore[method-assign]
    try:
        for seed in range(n):
            recorded.append([])  # the subproblems of one problem, in order
            solve_problem(scenario, scenario.sample(np.random.default_rng(seed)), backend="piqp")
    finally:
        qp_module.PIQPSolver.solve = original  # type: ignore[method-assign]
    count = sum(len(problem) for problem in recorded)
    out: dict = {"scenario": name, "problems": n, "subproblems": count}
    RiccatiSolver(recorded[0][0][0]).solve(recorded[0][0][1])  # compile or load the kernel outside the timing
    makers = {"piqp": qp_module.PIQPSolver, "riccati": RiccatiSolver}
    solvers: dict = {label: {} for label in makers}
    cpu = dict.fromkeys(makers, 0.0)
    iters: dict = {label: [] for label in makers}
    objs: dict = {label: [] for label in makers}
    # problem by problem, each backend solving a problem's subproblems in a row as in a solve (restarted first, as
    # the engine does), alternating which backend goes first; the least of 3 repeats per problem: the VM's speed
    # drifts by tens of per cent over minutes
    for i, problem in enumerate(recorded):
        for label in list(makers)[i % 2 :] + list(makers)[: i % 2]:
            best = np.inf
            for _ in range(3):
                spent = 0.0
                its, values = [], []
                for j, (spec, data) in enumerate(problem):
                    if spec not in solvers[label]:
                        solvers[label][spec] = makers[label](spec)
                    solver = solvers[label][spec]
                    if j == 0 or spec != problem[j - 1][0]:  # a new SCP solve (REL, then SCP)
                        solver.restart()
                    t0 = time.process_time()
                    _, _, sol = solver.solve(data)
                    spent += time.process_time() - t0
                    values.append(sol.objective)
                    if label == "piqp":
                        its.append(solver.solver.result.info.iter)
                    else:
                        its.append(status_iterations(sol.status))
                best = min(best, spent)
            cpu[label] += best
            iters[label] += its
            objs[label] += values
    for label in makers:
        out[label] = {
            "cpu_ms_per_subproblem": 1e3 * cpu[label] / count,
            "mean_iterations": float(np.mean(iters[label])),
        }
    objectives = {label: np.array(v) for label, v in objs.items()}
    out["speedup"] = out["piqp"]["cpu_ms_per_subproblem"] / out["riccati"]["cpu_ms_per_subproblem"]
    a, b = objectives["riccati"], objectives["piqp"]
    out["max_rel_objective_diff"] = float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-9)))
    print(
        f"[subproblems {name}, {count} from {n} problems] CPU per subproblem: PIQP "
        f"{out['piqp']['cpu_ms_per_subproblem']:.2f} ms ({out['piqp']['mean_iterations']:.1f} it.), riccati "
        f"{out['riccati']['cpu_ms_per_subproblem']:.2f} ms ({out['riccati']['mean_iterations']:.1f} it.): "
        f"x{out['speedup']:.2f}; objectives within {out['max_rel_objective_diff']:.1e}",
        flush=True,
    )
    return out


def _cost_vs(a: np.ndarray, b: np.ndarray) -> dict:
    """Relative cost differences of a against b on the problems both solved."""
    both = np.isfinite(a) & np.isfinite(b)
    rel = (a[both] - b[both]) / b[both]
    return {
        "median_rel_diff": float(np.median(rel)),
        "rel_diff_of_medians": float(np.median(a[both]) / np.median(b[both]) - 1),
        "worse_by_1pct": int(np.sum(rel > 0.01)),
        "better_by_1pct": int(np.sum(rel < -0.01)),
    }


def _ours(scenario, problem, backend: str) -> tuple[int, float, bool]:
    rel, scp = solve_problem(scenario, problem, backend=backend)
    ok = scp is not None and scp.success
    return rel.iterations + (scp.iterations if scp else 0), scp.cost if ok else np.nan, ok


def _nlp_peer(peer, scenario, problem) -> tuple[int, float, bool]:
    rel, full = peer.solve(problem)
    return rel.iterations + full.iterations, scenario.cost(full.U), full.ok


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peer-problems", type=int, default=30, help="problems per scenario in the peer comparison")
    ap.add_argument("--naive-problems", type=int, default=2, help="problems for the (slow) naive baseline")
    ap.add_argument("--robustness", type=int, default=200)
    ap.add_argument("--subproblem-problems", type=int, default=6, help="problems whose subproblems are re-solved")
    ap.add_argument("--engine-problems", type=int, default=10, help="problems per scenario, reference vs compiled")
    ap.add_argument(
        "--only",
        choices=["peer", "robustness", "subproblems", "engine", "naive"],
        help="run one part (merged into --out)",
    )
    ap.add_argument("--scenarios", default=",".join(list_scenarios()))
    ap.add_argument("--out", default=str(result_path("solver_speed")))
    args = ap.parse_args()
    machine = Machine()
    # --only re-runs one part and keeps the others from the previous result file
    result: dict = read_result(args.out) if args.only else {}
    scenarios = args.scenarios.split(",")
    loads = result.setdefault("load_average", {})  # per part: (start, end) 1/5/15-minute load averages
    if args.only in (None, "peer"):
        start = os.getloadavg()
        result["peer"] = {name: peer(name, args.peer_problems) for name in scenarios if name in PEER_SCENARIOS}
        loads["peer"] = (start, os.getloadavg())
    if args.only in (None, "robustness") and args.robustness:
        start = os.getloadavg()
        result["robustness"] = {
            name: robustness(name, args.robustness, reference=name == "freeflyer", backend="piqp")
            for name in scenarios
            if name in PEER_SCENARIOS
        }
        result["robustness_riccati"] = {
            name: robustness(name, args.robustness, reference=False, backend="riccati")
            for name in scenarios
            if name in PEER_SCENARIOS
        }
        loads["robustness"] = (start, os.getloadavg())
    if args.only in (None, "subproblems"):
        start = os.getloadavg()
        result["subproblems"] = {
            name: subproblems(name, args.subproblem_problems) for name in scenarios if name in PEER_SCENARIOS
        }
        loads["subproblems"] = (start, os.getloadavg())
    if args.only in (None, "engine"):
        from engine_paths import engine

        start = os.getloadavg()
        result["engine"] = {name: engine(name, args.engine_problems) for name in scenarios if name in PEER_SCENARIOS}
        loads["engine"] = (start, os.getloadavg())
    if args.only in (None, "naive"):
        start = os.getloadavg()
        result["naive"] = {name: speed(name, args.naive_problems, args.naive_problems) for name in scenarios}
        loads["naive"] = (start, os.getloadavg())
    headline: dict = {}
    for name, row in result.get("peer", {}).items():
        key = {"freeflyer": "ff", "quadrotor": "quad"}[name]
        headline[f"{key}_speedup_vs_ipopt"] = row["speedup_vs_ipopt"]
        headline[f"{key}_median_s"] = row["ours"]["median_s"]
        headline[f"{key}_ipopt_median_s"] = row["ipopt"]["median_s"]
        headline[f"{key}_iterations"] = row["ours"]["mean_iterations"]
        headline[f"{key}_ipopt_iterations"] = row["ipopt"]["mean_iterations"]
        headline[f"{key}_cost_vs_ipopt_median_rel"] = row["cost_vs_ipopt"]["median_rel_diff"]
        if "riccati" in row:
            headline[f"{key}_riccati_speedup_vs_ipopt"] = row["riccati_speedup_vs_ipopt"]
            headline[f"{key}_riccati_median_s"] = row["riccati"]["median_s"]
            headline[f"{key}_riccati_cost_vs_ipopt_median_rel"] = row["riccati_cost_vs_ipopt"]["median_rel_diff"]
        if "fatrop" in row:
            headline[f"{key}_riccati_speedup_vs_fatrop"] = row["riccati_speedup_vs_fatrop"]
            headline[f"{key}_riccati_cpu_speedup_vs_fatrop"] = row["riccati_cpu_speedup_vs_fatrop"]
            headline[f"{key}_fatrop_median_s"] = row["fatrop"]["median_s"]
            headline[f"{key}_fatrop_iterations"] = row["fatrop"]["mean_iterations"]
            headline[f"{key}_fatrop_failures"] = row["fatrop"]["failures"]
            headline[f"{key}_fatrop_cost_vs_riccati_median_rel"] = row["fatrop_cost_vs_riccati"]["median_rel_diff"]
    for name, row in result.get("robustness", {}).items():
        headline[f"{name}_failures_of_{args.robustness}"] = row["penalized"]["failures"]
    for name, row in result.get("robustness_riccati", {}).items():
        headline[f"{name}_riccati_failures_of_{args.robustness}"] = row["penalized"]["failures"]
    for name, row in result.get("subproblems", {}).items():
        headline[f"{name}_riccati_subproblem_speedup"] = row["speedup"]
    for name, row in result.get("engine", {}).items():
        headline[f"{name}_compiled_engine_ratio"] = row["ratio"]
        headline[f"{name}_compiled_engine_same_results"] = row["same_statuses"] and row["max_abs_dX"] == 0.0
        if "warm_start" in row:
            headline[f"{name}_warm_start_ip_iterations_ratio"] = row["warm_start"]["ip_iterations_ratio"]
        for H, w in row.get("windows", {}).items():
            headline[f"{name}_compiled_window{H}_ratio"] = w["ratio"]
    for name, row in result.get("naive", {}).items():
        headline[f"{name}_speedup_per_iter_vs_naive"] = row["speedup_per_iter"]
    result["headline"] = headline
    result["machine"] = machine.record()
    write_result(result, args.out, line=headline)


if __name__ == "__main__":
    main()
