"""The Riccati backend's per-iteration Python around its kernel, the NumPy reference against the compiled path, in
one run (``solver_speed.py --only engine``, part 4 there): REL + SCP per problem and MPC windows (H = 10, 30) from
their solutions, and the kernel's distance from its arithmetic; and its warm start between SCP iterations against
cold starts (``warm_starts``)."""

from __future__ import annotations

import time

import numpy as np
from engine_limit import kernel_flops

from ttompc.scenarios import Window, get_scenario
from ttompc.solvers import SCPProblem, TerminalCost, solve_problem, solve_scp
from ttompc.solvers.backends import riccati_kernel
from ttompc.solvers.backends.riccati import WARM, RiccatiSolver, status_iterations


def engine(name: str, n: int) -> dict:
    """REL + SCP per problem with the reference (NumPy) and the compiled per-iteration path of the Riccati backend,
    interleaved; CPU time, equality of the results, interior-point iterations, the kernel's flop rate."""
    scenario = get_scenario(name)
    kernel = {"cpu_s": 0.0}
    calls: list = []  # (stage QP, interior-point iterations) of every kernel call, counted after the timing
    original = riccati_kernel.solve

    def timed(qp, y, pi, options, state=None):
        t0 = time.process_time()
        out = original(qp, y, pi, options, state)
        kernel["cpu_s"] += time.process_time() - t0
        calls.append((qp, out.iterations))
        return out

    paths = {"reference": False, "compiled": True}
    rows: dict[str, list] = {k: [] for k in paths}
    solved: list = []  # (problem, its last solve by the second path)
    out: dict = {"scenario": name, "problems": n}
    warm = scenario.sample(np.random.default_rng(10_000))
    for compiled in paths.values():  # imports, structure caches and compiled code outside the timing
        RiccatiSolver.compiled = compiled
        solve_problem(scenario, warm)
    riccati_kernel.solve = timed
    try:
        for i in range(n):
            p = scenario.sample(np.random.default_rng(i))
            for label in list(paths)[i % 2 :] + list(paths)[: i % 2]:
                RiccatiSolver.compiled = paths[label]
                kernel_before = kernel["cpu_s"]
                c0 = time.process_time()
                rel, scp = solve_problem(scenario, p)
                cpu = time.process_time() - c0
                runs = [rel] if scp is None else [rel, scp]
                ip = [k for r in runs for h in r.history if (k := status_iterations(h.solver_status)) is not None]
                rows[label].append((cpu, kernel["cpu_s"] - kernel_before, runs, ip))
            solved.append((p, runs[-1]))
    finally:
        riccati_kernel.solve = original
        RiccatiSolver.compiled = True
    out["windows"] = {H: windows(scenario, solved, H) for H in (10, 30)}
    out["warm_start"] = warm_starts(scenario, n)
    for label, r in rows.items():
        cpus, kcpus = np.array([x[0] for x in r]), np.array([x[1] for x in r])
        ip = [k for x in r for k in x[3]]
        out[label] = {
            "median_cpu_ms": float(1e3 * np.median(cpus)),
            "kernel_share": float(kcpus.sum() / cpus.sum()),
            "subproblems_per_problem": len(ip) / n,
            "ip_iterations_per_subproblem": float(np.mean(ip)),
        }
    ref, comp = rows["reference"], rows["compiled"]
    out["ratio"] = out["reference"]["median_cpu_ms"] / out["compiled"]["median_cpu_ms"]
    out["same_statuses"] = all(
        [x.status for x in a[2]] == [x.status for x in b[2]]
        and [x.iterations for x in a[2]] == [x.iterations for x in b[2]]
        for a, b in zip(ref, comp, strict=True)
    )
    out["max_abs_dX"] = max(
        float(np.max(np.abs(x.X - y.X)))
        for a, b in zip(ref, comp, strict=True)
        for x, y in zip(a[2], b[2], strict=True)
    )
    out["kernel_us_per_ip_iteration"] = 1e6 * kernel["cpu_s"] / sum(its for _, its in calls)
    out["kernel_flops_per_ip_iteration"] = float(np.mean([kernel_flops(qp)["total"] for qp, _ in calls]))
    out["kernel_gflops"] = sum(its * kernel_flops(qp)["total"] for qp, its in calls) / kernel["cpu_s"] / 1e9
    print(
        f"[engine {name}, {n} problems] CPU ms per problem (median): reference {out['reference']['median_cpu_ms']:.1f},"
        f" compiled {out['compiled']['median_cpu_ms']:.1f}: x{out['ratio']:.2f}; same statuses {out['same_statuses']},"
        f" max |dX| {out['max_abs_dX']:.1e} | kernel {100 * out['compiled']['kernel_share']:.0f}% of the compiled"
        f" path, {out['compiled']['ip_iterations_per_subproblem']:.1f} IP it. per subproblem,"
        f" {out['kernel_us_per_ip_iteration']:.0f} us per IP it. ({out['kernel_gflops']:.2f} GFLOP/s) | MPC windows "
        + ", ".join(f"H = {H}: x{w['ratio']:.2f} (same {w['same']})" for H, w in out["windows"].items()),
        flush=True,
    )
    w = out["warm_start"]
    print(
        f"[engine {name}, warm start] IP it. per subproblem: cold {w['cold']['ip_iterations_per_subproblem']:.2f},"
        f" warm {w['warm']['ip_iterations_per_subproblem']:.2f} (later subproblems: cold"
        f" {w['cold']['ip_iterations_per_later_subproblem']:.2f},"
        f" warm {w['warm']['ip_iterations_per_later_subproblem']:.2f});"
        f" same statuses {w['same_statuses']}, largest relative cost difference {w['max_rel_cost_diff']:.1e}",
        flush=True,
    )
    return out


def warm_starts(scenario, n: int) -> dict:
    """REL + SCP per problem with the Riccati backend's warm start between SCP iterations (``RiccatiSolver.warm``, the
    default) and with cold starts, the same seeded problems, interleaved: interior-point iterations per subproblem
    (all, and the later ones of each solve: the first starts cold either way), subproblems per problem, median CPU ms
    per problem, whether statuses and SCP iterations agree, and the largest relative difference of REL's and SCP's
    costs."""
    modes = {"cold": 0.0, "warm": WARM}
    rows: dict[str, list] = {k: [] for k in modes}
    try:
        for i in range(n):
            p = scenario.sample(np.random.default_rng(i))
            for label in list(modes)[i % 2 :] + list(modes)[: i % 2]:
                RiccatiSolver.warm = modes[label]
                c0 = time.process_time()
                rel, scp = solve_problem(scenario, p)
                cpu = time.process_time() - c0
                runs = [rel] if scp is None else [rel, scp]
                ip = [[k for h in r.history if (k := status_iterations(h.solver_status)) is not None] for r in runs]
                rows[label].append((cpu, runs, ip))
    finally:
        RiccatiSolver.warm = WARM
    out: dict = {"problems": n, "delta": WARM}
    for label, r in rows.items():
        ip = [k for x in r for run in x[2] for k in run]
        later = [k for x in r for run in x[2] for k in run[1:]]
        out[label] = {
            "median_cpu_ms": float(1e3 * np.median([x[0] for x in r])),
            "subproblems_per_problem": len(ip) / n,
            "ip_iterations_per_subproblem": float(np.mean(ip)),
            "ip_iterations_per_later_subproblem": float(np.mean(later)),
        }
    pairs = [(a, b) for x, y in zip(rows["cold"], rows["warm"], strict=True) for a, b in zip(x[1], y[1], strict=True)]
    out["same_statuses"] = len(rows["cold"]) == len(rows["warm"]) and all(
        (a.status, a.iterations) == (b.status, b.iterations) for a, b in pairs
    )
    out["max_rel_cost_diff"] = max(abs(a.cost - b.cost) / max(abs(a.cost), 1e-12) for a, b in pairs)
    out["ip_iterations_ratio"] = (
        out["warm"]["ip_iterations_per_subproblem"] / out["cold"]["ip_iterations_per_subproblem"]
    )
    return out


def windows(scenario, solved: list, H: int) -> dict:
    """MPC windows of H steps at steps 10, 40 and 70 of each solution (soft mode, a 2-norm terminal term of weight 10
    on the solution's state at the window's end, from the solution: a converged receding-horizon step) by both
    paths, alternating, the least of 3: CPU ms per window, the ratio, equal statuses and iterates."""
    cases = []
    for problem, sol in solved:
        for t in (10, 40, 70):
            window = Window(t, H, len(sol.U))
            scp = SCPProblem(scenario, problem, window, TerminalCost(sol.X[t + H], 10.0), soft=True)
            cases.append((scp, sol.X[t : t + H + 1].copy(), sol.U[t : t + H].copy()))
    cpu: dict[bool, list[float]] = {False: [], True: []}
    results: dict[bool, list] = {}
    try:
        for rep in range(3):
            for compiled in (False, True)[rep % 2 :] + (False, True)[: rep % 2]:
                RiccatiSolver.compiled = compiled
                c0 = time.process_time()
                results[compiled] = [solve_scp(*case) for case in cases]
                cpu[compiled].append((time.process_time() - c0) / len(cases))
    finally:
        RiccatiSolver.compiled = True
    same = all(
        a.status == b.status and np.array_equal(a.X, b.X) for a, b in zip(results[False], results[True], strict=True)
    )
    ref, comp = 1e3 * min(cpu[False]), 1e3 * min(cpu[True])
    return {"windows": len(cases), "reference_cpu_ms": ref, "compiled_cpu_ms": comp, "ratio": ref / comp, "same": same}
