"""The SCP engine's measured limit (issue "engine"): how far REL + SCP with the Riccati kernel (the default backend)
could go against built-once IPOPT, from what one interior-point iteration costs against its arithmetic and what of a
solve is still Python. Free-flyer and quadrotor, the same seeded problems (0 .. ``--problems`` − 1) in every part.

Usage::

    nice -n 19 env OMP_NUM_THREADS=1 .venv/bin/python bench/engine_limit.py              # 20 problems a scenario
    .venv/bin/python bench/engine_limit.py --quick                                       # smoke run, no result file

1. Arithmetic (``arithmetic``): every stage QP the kernel solves in REL + SCP of the first ``--kernel-problems``
   problems, captured (copied with its start, warm or cold), re-solved ``--repeats`` times: the median CPU time per
   call over the kernel's interior-point iterations (``us_per_ip_iteration``). Its floating-point operations per
   iteration (``kernel_flops``, counted from the loops of ``riccati_kernel`` and ``riccati_rows``, by part) give the
   achieved GFLOP/s and its fraction of one core's peak: ``peak`` assumes the nominal clock of the CPU's model name,
   two FMA units and the widest vectors its flags name (AVX-512: 8 doubles, AVX2: 4), and the scalar FMA peak (one
   double a lane) beside it. The same QPs without their constraints (``Boxes.none``, ``Rows.none``; tolerances 0 so
   the kernel runs the same number of iterations) time the dense recursion alone (``recursion_us_per_ip_iteration``);
   the rest is the constraint passes. Divisions and square roots (``divisions``) are counted apart: they take 4-16
   cycles each, not one.
2. Python (``python``): REL + SCP per problem, the library's functions timed as nested regions of this process's CPU
   time (``timed_regions.Profiler``, monkeypatched, restored at the end): ``kernel`` (``riccati_kernel.solve``),
   ``linearise`` (the scenario's ``convex_model`` and ``constraints``), ``gather`` (the subproblem's data and the
   kernel's stage QP, ``StageQP.build``), ``objective`` (``StageQP.objective``), ``merit`` (merit, nonlinear
   violation, cost), ``subproblem`` (the Riccati backend's own Python), ``solver_lookup`` and ``engine`` (the rest of
   REL + SCP: guesses, checks, iterate records, results). Shares of the total; then a ``cProfile`` run of the same
   problems (``cprofile``, timed by CPU): its shares of the kernel, the other compiled (numba) functions (the build's
   ``riccati_build``, in ``gather``), Python functions and the C functions they call (NumPy's; ``builtin``), and the
   top 5 Python functions by self time (cProfile inflates Python: its total is beside the untimed one).
3. Ceiling (``ceiling``): ours and IPOPT (``ipopt_peer.IpoptPeer``, built once) on the same problems, interleaved,
   median CPU ms per problem, and their ratio ``speedup_vs_ipopt`` S. With the kernel's share f of ours (part 2) and
   its fraction φ of peak (part 1): S / f if the Python went to zero (Amdahl), S / ((1 − f) + f·φ) if the kernel ran
   at its arithmetic, and what 10× needs: the kernel's speedup with the Python as it is and with none, the Python's
   with the kernel as it is (None where that alone cannot reach it).

Ends with one JSON line, also written to bench/results/engine_limit.json (not with ``--quick``: 2 problems, 1 kernel
problem, 2 repeats) with the machine record (``bench/record.py``). The ratios and shares are the figures to compare;
absolute times need a quiet machine.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import re
import sys
import time
from pathlib import Path

import numpy as np
from record import Machine, result_path, write_result
from timed_regions import Profiler

from ttompc.scenarios import get_scenario
from ttompc.solvers import engine, solve_problem
from ttompc.solvers.backends import riccati_kernel
from ttompc.solvers.backends.riccati import RiccatiSolver, StageQP
from ttompc.solvers.backends.riccati_qp import Boxes, RiccatiOptions, Rows

SCENARIOS = ("freeflyer", "quadrotor")
ROOT = Path(__file__).resolve().parent.parent

# flops of one pass over a constraint, (hard, soft), by family (riccati_rows: a box, a row of width w)
BOX = {"residuals": (20, 22), "weights": (19, 20), "rhs": (17, 17), "steps": (20, 26)}


def row_flops(w: int) -> dict[str, tuple[int, int]]:
    """``BOX`` for a row of width w."""
    return {
        "residuals": (4 * w + 17, 4 * w + 19),
        "weights": (2 * w * w + 3 * w + 14, 2 * w * w + 3 * w + 15),
        "rhs": (2 * w + 15, 2 * w + 15),
        "steps": (2 * w + 19, 2 * w + 25),
    }


def kernel_flops(qp) -> dict[str, float]:
    """Floating-point operations of one interior-point iteration of the Riccati kernel (``riccati_kernel._ipm``) on
    ``qp``, by part, counted from its loops and its constraint passes' (``riccati_rows``): an add, multiply, divide or
    square root is 1, a multiply-add 2; comparisons, abs and max are not counted, nor a ratio test's division (taken
    only where it binds), nor the terminal cone's (MPC windows only; O(NX²) once). Parts: ``residuals``, ``hessians``
    (with the constraints' weights), ``factorisation``, ``solves`` (predictor and corrector: backward pass, forward
    rollout; with the corrector's right-hand side), ``steps`` (the constraints' steps, twice), ``update``; sums
    ``recursion`` (the dense stage arithmetic) and ``constraints`` (the passes over boxes and rows), ``total``; and
    ``divisions`` (divides and square roots among them)."""
    N, n, nu = qp.shape
    ny = n + nu
    qn = qp.cost.QN.shape[0] > 0
    chol = sum(2 * j + 1 + (nu - 1 - j) * (2 * j + 1) for j in range(nu))  # _chol
    cho_solve = 2 * nu * nu  # _cho_solve
    dense = {
        "residuals": (N + 1) * ny * 3  # Qd y + q, stationarity's probe
        + (2 * n * n if qn else 0)
        + N * n * (2 * ny + 2)  # A x + B u + c − x⁺
        + N * n * (2 * n + 2)  # Aᵀπ, −π
        + N * nu * (2 * n + 1),  # Bᵀπ
        "hessians": (N + 1) * ny + (n * n if qn else 0),
        "factorisation": N
        * (2 * n**3 + 2 * n * n * nu + 2 * nu * nu * n + 2 * nu * n * n + chol + n * cho_solve + n * (n + 1) * ny),
        "solves": 2 * N * (4 * n * n + 4 * n * nu + cho_solve) + 2 * N * (2 * n * n + 4 * n * nu),
        "steps": 0,
        "update": N * n * 2 * n + (N + 1) * ny * 2 + N * n * 2,
    }
    soft_b, soft_r = int((qp.boxes.rho > 0).sum()), int((qp.rows.rho > 0).sum())
    nb, nr = qp.boxes.d.shape[0], qp.rows.d.shape[0]
    rows = row_flops(qp.rows.cols.shape[1])
    per = {
        p: (nb - soft_b) * BOX[p][0] + soft_b * BOX[p][1] + (nr - soft_r) * rows[p][0] + soft_r * rows[p][1]
        for p in BOX
    }
    passes = {
        "residuals": per["residuals"],
        "hessians": per["weights"],
        "solves": per["rhs"],
        "steps": 2 * per["steps"],
    }
    out: dict[str, float] = {p: float(dense[p] + passes.get(p, 0)) for p in dense}
    out["recursion"] = float(sum(dense.values()))
    out["constraints"] = float(sum(passes.values()))
    out["total"] = out["recursion"] + out["constraints"]
    out["divisions"] = float(
        N * (nu * (nu + 1) // 2 + n * 2 * nu)  # _chol, the gains' solves
        + 2 * N * 2 * nu  # the backward passes' solves
        + 2 * (nb + nr)
        + soft_b
        + soft_r  # 1/λ, 1/(s/λ + e/μ), and 1/μ where soft
    )
    return out


def core_peak() -> dict:
    """One core's peak double-precision GFLOP/s as ``kernel_flops`` counts them (a multiply-add 2), from
    /proc/cpuinfo: the nominal clock in the model name (else the current one), two FMA units, the widest vector the
    flags name (``avx512f``: 8 doubles, ``avx2``: 4, else 2); and the scalar FMA peak."""
    text = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    found = re.search(r"^flags\s*:(.*)$", text, re.M)
    flags = set(found.group(1).split()) if found else set()
    nominal = re.search(r"^model name.*@\s*([\d.]+)GHz", text, re.M)
    current = re.search(r"^cpu MHz\s*:\s*([\d.]+)", text, re.M)
    ghz = float(nominal.group(1)) if nominal else float(current.group(1)) / 1e3 if current else float("nan")
    lanes, isa = (8, "AVX-512") if "avx512f" in flags else (4, "AVX2") if "avx2" in flags else (2, "SSE2")
    fma = 2 if "fma" in flags else 1
    return {
        "isa": isa,
        "fma": fma == 2,
        "ghz": ghz,
        "fma_units": 2,
        "vector_gflops": ghz * 2 * lanes * fma,
        "scalar_gflops": ghz * 2 * fma,
    }


def _copy_qp(x):
    """A deep copy of a stage QP (nested named tuples of arrays)."""
    return type(x)(*(_copy_qp(f) for f in x)) if isinstance(x, tuple) else np.array(x, copy=True)


def capture(scenario, seeds) -> list:
    """(stage QP, y, π, iterations, options, constraint state) of every kernel call of REL + SCP on ``seeds``, copied
    before the call (the state None for a cold start: ``RiccatiSolver.warm``)."""
    calls: list = []
    original = riccati_kernel.solve

    def captured(qp, y, pi, options, state=None):
        before = (_copy_qp(qp), y.copy(), pi.copy())
        start = None if state is None or options.warm == 0.0 else _copy_qp(state)
        out = original(qp, y, pi, options, state)
        calls.append((*before, out.iterations, options, start))
        return out

    riccati_kernel.solve = captured
    try:
        for seed in seeds:
            solve_problem(scenario, scenario.sample(np.random.default_rng(seed)))
    finally:
        riccati_kernel.solve = original
    return calls


def _time_calls(calls: list, repeats: int, strip: bool) -> tuple[float, int]:
    """Σ over calls of the median CPU seconds of a solve as the engine called it (its options and start), and Σ
    iterations; ``strip``: the QP without constraints, run cold for the captured iterations (tolerances 0)."""
    seconds, iterations = 0.0, 0
    for qp, y0, pi0, its, options, start in calls:
        if strip:
            qp = qp._replace(boxes=Boxes.none(), rows=Rows.none(qp.rows.cols.shape[1]))
            options, start = RiccatiOptions(0.0, 0.0, max(its, 1)), None
        times = []
        for _ in range(repeats):
            y, pi, state = y0.copy(), pi0.copy(), None if start is None else _copy_qp(start)
            c0 = time.process_time()
            out = riccati_kernel.solve(qp, y, pi, options, state)
            times.append(time.process_time() - c0)
        seconds += float(np.median(times))
        iterations += out.iterations
    return seconds, iterations


def arithmetic(scenario, seeds, repeats: int, peak: dict) -> dict:
    """Part 1 (the module docstring's)."""
    calls = capture(scenario, seeds)
    N, n, nu = calls[0][0].shape
    flops = [kernel_flops(qp) for qp, *_ in calls]
    its = np.array([c[3] for c in calls])
    mean = {k: float(np.average([f[k] for f in flops], weights=its)) for k in flops[0]}  # per iteration
    full_s, full_its = _time_calls(calls, repeats, strip=False)
    rec_s, rec_its = _time_calls(calls, repeats, strip=True)
    us, rec_us = 1e6 * full_s / full_its, 1e6 * rec_s / rec_its
    rec_flops = float(np.average([f["recursion"] for f in flops], weights=its))
    gflops = mean["total"] / us / 1e3
    qp = calls[-1][0]
    return {
        "N": N,
        "nx": n,
        "nu_kernel": nu,
        "boxes": int(qp.boxes.d.shape[0]),
        "rows": int(qp.rows.d.shape[0]),
        "row_width": int(qp.rows.cols.shape[1]),
        "subproblems": len(calls),
        "ip_iterations_per_subproblem": float(its.mean()),
        "flops_per_ip_iteration": mean,
        "flops_per_stage": mean["total"] / N,
        "us_per_ip_iteration": us,
        "recursion_us_per_ip_iteration": rec_us,
        "constraints_us_per_ip_iteration": us - rec_us,
        "gflops": gflops,
        "recursion_gflops": rec_flops / rec_us / 1e3,
        "constraints_gflops": mean["constraints"] / max(us - rec_us, 1e-9) / 1e3,
        "fraction_of_vector_peak": gflops / peak["vector_gflops"],
        "fraction_of_scalar_peak": gflops / peak["scalar_gflops"],
        "us_at_vector_peak": mean["total"] / peak["vector_gflops"] / 1e3,
        "us_at_4_cycles_a_division": mean["divisions"] * 4 / peak["ghz"] / 1e3,
    }


REGIONS = ("kernel", "linearise", "gather", "objective", "merit", "subproblem", "solver_lookup", "engine")


def python_share(scenario, seeds) -> dict:
    """Part 2: the regions' CPU ms per problem and shares; the cProfile run's top 5 Python functions by self time."""
    prof = Profiler(clock=time.process_time)
    patches = [
        (scenario, "convex_model", "linearise"),
        (scenario, "constraints", "linearise"),
        (scenario, "cost", "merit"),
        (engine, "_merit", "merit"),
        (engine, "_violation", "merit"),
        (engine, "_subproblem_data", "gather"),
        (StageQP, "build", "gather"),
        (StageQP, "objective", "objective"),
        (engine, "_subproblem_solver", "solver_lookup"),
        (RiccatiSolver, "solve", "subproblem"),
        (riccati_kernel, "solve", "kernel"),
    ]
    saved = [(obj, name, obj.__dict__.get(name)) for obj, name, _ in patches]  # None: the class's attribute
    run = prof.region("engine", solve_problem)
    for obj, name, region in patches:
        setattr(obj, name, prof.region(region, getattr(obj, name)))
    prof.on = True
    try:
        for seed in seeds:
            run(scenario, scenario.sample(np.random.default_rng(seed)))
    finally:
        prof.on = False
        for obj, name, old in saved:
            if old is None:
                delattr(obj, name)
            else:
                setattr(obj, name, old)
    by_region = dict.fromkeys(REGIONS, 0.0)
    for path, t in prof.self_times().items():
        by_region[path.rpartition("/")[2]] += t
    total = prof.incl["engine"]
    counts = {leaf: sum(c for p, c in prof.calls.items() if p.rpartition("/")[2] == leaf) for leaf in REGIONS}
    if counts["kernel"] != counts["subproblem"]:
        raise RuntimeError("a subproblem went past the Riccati kernel (its fallback): the shares would mix backends")
    out = {
        "cpu_ms_per_problem": {k: 1e3 * t / len(seeds) for k, t in by_region.items()},
        "share": {k: t / total for k, t in by_region.items()},
        "kernel_share": by_region["kernel"] / total,
        "python_share": 1.0 - by_region["kernel"] / total,
    }
    profile = cProfile.Profile(time.process_time)
    c0 = time.process_time()
    profile.enable()
    for seed in seeds:
        solve_problem(scenario, scenario.sample(np.random.default_rng(seed)))
    profile.disable()
    profiled = time.process_time() - c0
    stats = pstats.Stats(profile).stats  # type: ignore[attr-defined]
    kinds: dict[str, float] = {"kernel": 0.0, "compiled": 0.0, "python": 0.0, "builtin": 0.0}
    python = []
    for (file, line, func), (_, calls, tt, _, _) in stats.items():
        kind = _kind(file, func)
        kinds[kind] += tt
        if kind == "python":
            python.append((tt, calls, f"{_short(file)}:{line}({func})"))
    out["cprofile"] = {
        "cpu_ms_per_problem": 1e3 * profiled / len(seeds),
        "share": {k: t / profiled for k, t in kinds.items()},
        "top5_python_self": [
            {
                "function": name,
                "self_ms_per_problem": 1e3 * tt / len(seeds),
                "calls_per_problem": calls / len(seeds),
                "share_of_profiled": tt / profiled,
            }
            for tt, calls, name in sorted(python, reverse=True)[:5]
        ],
    }
    return out


def _kind(file: str, func: str) -> str:
    """What a cProfile entry times: ``kernel`` (the kernel's compiled entry point, a built-in to cProfile),
    ``compiled`` (a numba function: numba reports its calls to the profiler), ``builtin`` (another C function called
    from Python: NumPy's, the interpreter's), else ``python``."""
    if file == "~":
        return "kernel" if "riccati_kernel.solve_stage_qp" in func else "builtin"
    module = next((m for m in list(sys.modules.values()) if getattr(m, "__file__", None) == file), None)
    return "compiled" if hasattr(getattr(module, func, None), "py_func") else "python"


def _short(file: str) -> str:
    """A source path relative to the checkout (or to site-packages)."""
    path = Path(file)
    if path.is_relative_to(ROOT) and ".venv" not in path.parts:
        return str(path.relative_to(ROOT))
    return "/".join(path.parts[-2:])


def ceiling(scenario, seeds, kernel_share: float, fraction: dict[str, float]) -> dict:
    """Part 3: ours and built-once IPOPT on ``seeds``, interleaved, median CPU ms, and the ceilings from the kernel's
    share and its fraction of peak."""
    from ipopt_peer import IpoptPeer

    ipopt = IpoptPeer(scenario)
    runners = {"ours": lambda p: solve_problem(scenario, p), "ipopt": ipopt.solve}
    warm = scenario.sample(np.random.default_rng(10_000))
    for run in runners.values():  # imports, CasADi code generation outside the timing
        run(warm)
    cpu: dict[str, list[float]] = {k: [] for k in runners}
    for i, seed in enumerate(seeds):
        p = scenario.sample(np.random.default_rng(seed))
        for k in list(runners)[i % 2 :] + list(runners)[: i % 2]:
            c0 = time.process_time()
            runners[k](p)
            cpu[k].append(time.process_time() - c0)
    ours, peer = float(np.median(cpu["ours"])), float(np.median(cpu["ipopt"]))
    s, f = peer / ours, kernel_share
    target = s / 10  # ours' time, as a fraction of today's, at 10× IPOPT
    return {
        "ours_cpu_ms": 1e3 * ours,
        "ipopt_cpu_ms": 1e3 * peer,
        "speedup_vs_ipopt": s,
        "python_zero": s / f,
        "kernel_at_vector_peak": s / ((1 - f) + f * fraction["vector"]),
        "kernel_at_scalar_peak": s / ((1 - f) + f * fraction["scalar"]),
        "python_zero_kernel_at_scalar_peak": s / (f * fraction["scalar"]),
        "ten_x_kernel_speedup_python_as_is": f / (target - (1 - f)) if target > 1 - f else None,
        "ten_x_kernel_speedup_python_zero": f / target,
        "ten_x_python_speedup_kernel_as_is": (1 - f) / (target - f) if target > f else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--problems", type=int, default=20)
    ap.add_argument("--kernel-problems", type=int, default=5, help="problems whose stage QPs part 1 re-solves")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 problems, no result file")
    ap.add_argument("--out", default=str(result_path("engine_limit")))
    args = ap.parse_args()
    if min(args.problems, args.kernel_problems, args.repeats) < 1:
        ap.exit(2, "engine_limit: --problems, --kernel-problems and --repeats must be at least 1\n")
    if args.quick:
        args.problems, args.kernel_problems, args.repeats, args.out = 2, 1, 2, None
    machine, peak = Machine(), core_peak()
    seeds = range(args.problems)
    result: dict = {"problems": args.problems, "peak": peak, "scenarios": {}}
    for name in SCENARIOS:
        scenario = get_scenario(name)
        solve_problem(scenario, scenario.sample(np.random.default_rng(10_000)))  # compiled code outside the timing
        arith = arithmetic(scenario, range(args.kernel_problems), args.repeats, peak)
        py = python_share(scenario, seeds)
        fraction = {"vector": arith["fraction_of_vector_peak"], "scalar": arith["fraction_of_scalar_peak"]}
        result["scenarios"][name] = {
            "arithmetic": arith,
            "python": py,
            "ceiling": ceiling(scenario, seeds, py["kernel_share"], fraction),
        }
        print(f"[{name}] {_line(result['scenarios'][name])}", flush=True)
    result["machine"] = machine.record()
    line = {name: _line(r) for name, r in result["scenarios"].items()} | {
        "isa": peak["isa"],
        "load": result["machine"]["load_average"],
    }
    write_result(result, args.out, line)


def _line(r: dict) -> dict:
    """A scenario's headline figures."""
    a, p, c = r["arithmetic"], r["python"], r["ceiling"]
    return {
        "flops_per_stage": round(a["flops_per_stage"]),
        "us_per_ip_it": round(a["us_per_ip_iteration"], 1),
        "gflops": round(a["gflops"], 2),
        "of_vector_peak": round(a["fraction_of_vector_peak"], 4),
        "of_scalar_peak": round(a["fraction_of_scalar_peak"], 3),
        "kernel_share": round(p["kernel_share"], 3),
        "vs_ipopt": round(c["speedup_vs_ipopt"], 2),
        "python_zero": round(c["python_zero"], 2),
        "kernel_at_vector_peak": round(c["kernel_at_vector_peak"], 2),
    }


if __name__ == "__main__":
    main()
