"""Per-step MPC time of REL-MPC, DIST-MPC and TTO-MPC at H = 10 and H = 30, measured in the same run (paper Fig. 6
and the "~7x" claim: REL-MPC needs H = 30 for the cost FT-TTO-MPC reaches at H = 10).

Step time = observe of the previous step's outcome + warm start + windowed SCP (``Episode.step_times``; perf_counter;
CUDA synchronised inside the TTO provider). Per episode we take the mean and the max over its steps (the paper plots
the average over problems of the per-episode max); the ratio REL-MPC@30 / FT-TTO-MPC@10 is reported for both.
Without ``--checkpoint`` the transformer is a *randomly initialised* model of the chosen size: its step times are
right for that architecture, but its warm starts are poor, so the SCP part of TTO-MPC (iterations) is not
representative — pass a fine-tuned model for the real claim.

Threads: a batch-1 rollout is a chain of tiny matmuls; with 2 OpenMP threads on a shared 2-core machine we measured
a 10-step rollout of a 0.6M-parameter model at 4.2 s against 46 ms with one thread (spin-waiting under
oversubscription), so the default is one torch thread.

``--episode-cost``: the CPU-seconds per closed-loop episode of ``ttompc evaluate mpc`` (every method of the protocol,
both plants, the first horizon) on the same problems, measured in the same run two ways: *before*, one problem at a
time (each episode alone, as the evaluation ran before batching) and *after*, all problems in lockstep
(``run_problems``: one batched rollout per step for each TTO method, the solver structures of the first problem
serving the others). Each way starts with an empty solver-structure cache, so neither inherits what the other built.
CPU-seconds are this process's (``time.process_time``), so a loaded machine changes them less than the wall time.

Plan reuse and RTI rows, at the first horizon, in the same run: ``REL-MPC[today]`` is REL-MPC re-solving every
step (``reuse=false``); ``REL-MPC[rti]`` and ``<TTO>[rti]`` are real-time iteration (one subproblem per step from
the previous solution shifted; a departure from the paper), beside their converged rows. ``--episode-cost``
then also runs the batched protocol with ``rti=true``, and its *before* re-solves every step (``reuse=false``).

``--dagger R``: CPU-seconds per DAgger rollout with labels (``collect_rollout``: 100 steps, the learner the
model, default exploration) for R rollouts, each collected twice in the same run, alternating: the expert
re-solving every step (``reuse=false``) and with plan reuse; plus the largest label difference between the two.

The default backend is the Riccati interior-point kernel; ``REL-MPC[piqp]`` (and a third DAgger timing) run the
PIQP path (``backend="piqp"``, the default chain without the kernel) on the same problems.

``--quick``: a smoke run (tiny random model, 2 problems, 3 MPC steps, H = 10, with ``--episode-cost``; no result
file).

Ends with one JSON line, also written to bench/results/mpc_speed.json (not with ``--quick``).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
import torch
from record import Machine, result_path, write_result

from ttompc.evaluation.closed_loop import ClosedLoopConfig, episodes_per_problem, run_problems
from ttompc.evaluation.problems import EvalProblem, eval_problem
from ttompc.finetune.collect import collect_rollout
from ttompc.finetune.config import ExplorationConfig
from ttompc.mpc import DISTProvider, MPCSettings, RELProvider, TTOProvider, run_mpc
from ttompc.policy import ModelConfig, Planner, TrajectoryGPT
from ttompc.scenarios import Scenario, get_scenario
from ttompc.solvers.backends import clear_solver_cache

SIZES = {
    "paper": {},
    "small": {"n_embd": 128, "n_layer": 3, "n_head": 4},
    "tiny": {"n_embd": 64, "n_layer": 2, "n_head": 4},
}


def random_planner(scenario_name: str, size: str, device: str) -> Planner:
    """A randomly initialised model (timing only) with identity-like normalisation."""
    from ttompc.policy.stats import NormStats

    sc = get_scenario(scenario_name)
    torch.manual_seed(0)
    model = TrajectoryGPT(
        ModelConfig(state_dim=sc.state_dim, control_dim=sc.control_dim, max_steps=sc.n_steps, **SIZES[size])
    )
    n, m = sc.state_dim, sc.control_dim
    stats = NormStats(
        mean={"states": np.zeros(n), "actions": np.zeros(m), "goals": np.zeros(n), "rtg": [0.0], "ctg": [0.0]},
        std={"states": np.ones(n), "actions": np.full(m, 1e-3), "goals": np.ones(n), "rtg": [1.0], "ctg": [1.0]},
    )
    return Planner(model.to(device), sc, stats)


def episode_cost(
    scenario: Scenario,
    problems: list[EvalProblem],
    planner: Planner,
    horizon: int,
    max_steps: int | None,
    end_horizon: int = 0,
) -> dict[str, float]:
    """CPU- and wall-seconds per closed-loop episode of the protocol: one problem at a time re-solving every step
    (no batching, no plan reuse) vs batched with plan reuse, and batched with real-time iteration (module doc)."""
    cfg = ClosedLoopConfig(
        scenario=scenario.name,
        horizons=[horizon],
        max_steps=max_steps,
        batch=len(problems),
        mpc={"end_horizon": end_horizon},
    )
    models = {"TTO": planner}
    episodes = len(problems) * episodes_per_problem(cfg, models)
    out: dict[str, float] = {"episodes": episodes, "end_horizon": end_horizon}
    runs = (
        ("before", [[ep] for ep in problems], dataclasses.replace(cfg, mpc={**cfg.mpc, "reuse": False})),
        ("after", [problems], cfg),
        ("after_rti", [problems], dataclasses.replace(cfg, mpc={**cfg.mpc, "rti": True})),
    )
    for label, tasks, c in runs:
        clear_solver_cache()
        cpu, wall = time.process_time(), time.perf_counter()
        for task in tasks:
            run_problems(scenario, task, models, c)
        out[f"{label}_cpu_s_per_episode"] = (time.process_time() - cpu) / episodes
        out[f"{label}_wall_s_per_episode"] = (time.perf_counter() - wall) / episodes
    for label in ("after", "after_rti"):
        out[f"cpu_ratio_{label}_over_before"] = out[f"{label}_cpu_s_per_episode"] / out["before_cpu_s_per_episode"]
    return out


def dagger_cost(scenario: Scenario, planner: Planner, rollouts: int, seed: int) -> dict[str, float]:
    """CPU-seconds per DAgger rollout with labels, the expert re-solving every step vs with plan reuse, alternating
    per rollout (module doc), and the largest difference between their labels."""
    runs = [("before", False, "auto"), ("after", True, "auto"), ("piqp", True, "piqp")]
    cpu = {label: 0.0 for label, _, _ in runs}
    diff = {label: 0.0 for label, _, _ in runs[1:]}
    for r in range(rollouts):
        rows = {}
        for label, reuse, backend in runs[r % len(runs) :] + runs[: r % len(runs)]:  # rotate who goes first
            t0 = time.process_time()
            rows[label] = collect_rollout(
                scenario, planner, 0, r, seed, ExplorationConfig(), MPCSettings(reuse=reuse, backend=backend)
            )
            cpu[label] += time.process_time() - t0
        for label in diff:
            d = np.max(np.abs(rows[label]["target_actions"] - rows["before"]["target_actions"]))
            diff[label] = max(diff[label], float(d))
    out = {
        "rollouts": rollouts,
        "before_cpu_s_per_rollout": cpu["before"] / rollouts,
        "after_cpu_s_per_rollout": cpu["after"] / rollouts,
        "cpu_ratio_after_over_before": cpu["after"] / cpu["before"],
        "max_label_difference": diff["after"],
    }
    out["piqp_cpu_s_per_rollout"] = cpu["piqp"] / rollouts
    out["cpu_ratio_piqp_over_before"] = cpu["piqp"] / cpu["before"]
    out["max_label_difference_piqp"] = diff["piqp"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="freeflyer")
    ap.add_argument("--checkpoint", help="FT-TTO model (checkpoint, bundle or zoo name); default: random model")
    ap.add_argument("--size", choices=sorted(SIZES), default="paper", help="random model size (without --checkpoint)")
    ap.add_argument("--problems", type=int, default=2)
    ap.add_argument("--horizons", default="10,30")
    ap.add_argument("--max-steps", type=int, default=None, help="MPC steps per episode (default: all N)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--threads", type=int, default=1, help="torch threads (batch-1 rollouts gain nothing from more; see below)"
    )
    ap.add_argument("--episode-cost", action="store_true", help="CPU-seconds per protocol episode, before/after")
    ap.add_argument("--end-horizon", type=int, default=0, help="end_horizon of the --episode-cost protocol")
    ap.add_argument("--dagger", type=int, default=0, help="DAgger rollouts to time, before/after (0: none)")
    ap.add_argument("--quick", action="store_true", help="smoke run: tiny model, 2 problems, 3 steps, no result file")
    ap.add_argument("--out", default=str(result_path("mpc_speed")))
    args = ap.parse_args()
    if args.quick:
        args.size, args.problems, args.max_steps, args.horizons, args.episode_cost = "tiny", 2, 3, "10", True
    torch.set_num_threads(args.threads)

    sc = get_scenario(args.scenario)
    if args.checkpoint:
        planner = Planner.from_pretrained(args.checkpoint, device=args.device)
        model_desc, name = args.checkpoint, "FT-TTO-MPC"
    else:
        planner, model_desc = random_planner(args.scenario, args.size, args.device), f"random {args.size} (timing only)"
        name = "TTO-MPC"
    n_params = sum(p.numel() for p in planner.model.parameters())
    horizons = [int(h) for h in args.horizons.split(",")]
    problems = [eval_problem(sc, args.seed, i, nonconvex_only=True) for i in range(args.problems)]
    # (provider factory, solver backend, loop options); the bracketed variants run at the first horizon only:
    # "[conic]" the previous default solver path (QOCO/Clarabel, 2-norm trust region), "[today]" re-solving every
    # step (no plan reuse), "[rti]" real-time iteration
    providers = {
        "REL-MPC": (lambda: RELProvider(), "auto", {}),
        "DIST-MPC": (lambda: DISTProvider(), "auto", {}),
        name: (lambda: TTOProvider(planner, name), "auto", {}),
        "REL-MPC[today]": (lambda: RELProvider(), "auto", {"reuse": False}),
        "REL-MPC[rti]": (lambda: RELProvider(), "auto", {"rti": True}),
        f"{name}[rti]": (lambda: TTOProvider(planner, name), "auto", {"rti": True}),
        "REL-MPC[conic]": (lambda: RELProvider(backend="conic"), "conic", {}),
    }
    # "[piqp]": the PIQP path, the default chain without the kernel (the default runs the Riccati kernel where it can)
    providers["REL-MPC[piqp]"] = (lambda: RELProvider(backend="piqp"), "piqp", {})
    # warm-up (imports, solver structure caches, torch kernels) outside the timing
    for make, backend, opts in providers.values():
        run_mpc(
            sc,
            problems[0].problem,
            make(),
            horizons[0],
            rel_cost=problems[0].rel.cost,
            max_steps=2,
            settings=MPCSettings(backend=backend, **opts),
        )
    results: dict[str, dict[str, float]] = {}
    print(f"{sc.name}: {len(problems)} problems, model {model_desc} ({n_params / 1e6:.2f}M params, {args.device})")
    print(f"{'method':>11} {'H':>4} {'mean step [ms]':>15} {'max step [ms]':>14} {'warm [ms]':>10} {'cost':>9}")
    machine = Machine()
    for H in horizons:
        for method, (make, backend, opts) in providers.items():
            if method.endswith("]") and H != horizons[0]:
                continue
            cpu = time.process_time()
            eps = [
                run_mpc(
                    sc,
                    ep.problem,
                    make(),
                    H,
                    rel_cost=ep.rel.cost,
                    max_steps=args.max_steps,
                    settings=MPCSettings(backend=backend, **opts),
                )
                for ep in problems
            ]
            r = {
                "mean_step_s": float(np.mean([e.step_times.mean() for e in eps])),
                "max_step_s": float(np.mean([e.step_times.max() for e in eps])),
                "mean_warm_s": float(np.mean([e.warm_times.mean() for e in eps])),
                "cost": float(np.mean([e.cost for e in eps])),
                "feasible_rate": float(np.mean([e.feasible for e in eps])),
                "mean_iterations": float(np.mean([e.iterations.mean() for e in eps])),
                # CPU-s per step of this process: the wall-clock step times above mean little beside other jobs
                "cpu_s_per_step": (time.process_time() - cpu) / sum(len(e.U) for e in eps),
            }
            results[f"{method}@{H}"] = r
            print(
                f"{method:>11} {H:>4} {r['mean_step_s'] * 1e3:>15.1f} {r['max_step_s'] * 1e3:>14.1f} "
                f"{r['mean_warm_s'] * 1e3:>10.1f} {r['cost']:>9.4f}"
            )
    ratio = {}
    if "REL-MPC@30" in results and f"{name}@10" in results:
        ratio = {
            "mean": results["REL-MPC@30"]["mean_step_s"] / results[f"{name}@10"]["mean_step_s"],
            "max": results["REL-MPC@30"]["max_step_s"] / results[f"{name}@10"]["max_step_s"],
        }
        print(f"REL-MPC@30 / {name}@10 step time: mean {ratio['mean']:.2f}x, max {ratio['max']:.2f}x (paper: ~7x)")
    h0, speedup = horizons[0], None
    if f"REL-MPC[conic]@{h0}" in results:
        speedup = results[f"REL-MPC[conic]@{h0}"]["mean_step_s"] / results[f"REL-MPC@{h0}"]["mean_step_s"]
        print(f"REL-MPC@{h0}: previous conic solver path / default, mean step time {speedup:.2f}x")
    today = {}
    for variant in ("REL-MPC", "REL-MPC[rti]", "REL-MPC[piqp]", f"{name}[rti]"):
        ref = results.get(f"{name if variant.startswith(name) else 'REL-MPC[today]'}@{h0}")
        if ref and f"{variant}@{h0}" in results:
            today[variant] = results[f"{variant}@{h0}"]["cpu_s_per_step"] / ref["cpu_s_per_step"]
            print(
                f"{variant}@{h0} CPU-s per step / {'converged' if variant.startswith(name) else 'today'}: "
                f"{today[variant]:.2f}x"
            )
    cost = None
    if args.episode_cost:
        cost = episode_cost(sc, problems, planner, h0, args.max_steps, args.end_horizon)
        before = cost["before_cpu_s_per_episode"]
        print(
            f"closed-loop episode of the protocol (H = {h0}, end_horizon {args.end_horizon}, "
            f"{cost['episodes']:.0f} episodes): {before:.2f} CPU-s one problem at a time re-solving every step, "
            f"{cost['after_cpu_s_per_episode']:.2f} batched with reuse ({cost['cpu_ratio_after_over_before']:.2f}x), "
            f"{cost['after_rti_cpu_s_per_episode']:.2f} batched RTI "
            f"({cost['cpu_ratio_after_rti_over_before']:.2f}x)"
        )
    dagger = None
    if args.dagger:
        dagger = dagger_cost(sc, planner, args.dagger, args.seed)
        print(
            f"DAgger rollout with labels ({args.dagger} rollouts): {dagger['before_cpu_s_per_rollout']:.2f} CPU-s "
            f"re-solving every step, {dagger['after_cpu_s_per_rollout']:.2f} with plan reuse "
            f"({dagger['cpu_ratio_after_over_before']:.2f}x; labels differ by <= "
            f"{dagger['max_label_difference']:.1e})"
        )
        print(
            f"  with backend piqp: {dagger['piqp_cpu_s_per_rollout']:.2f} CPU-s "
            f"({dagger['cpu_ratio_piqp_over_before']:.2f}x; labels differ by <= "
            f"{dagger['max_label_difference_piqp']:.1e})"
        )
    summary = {
        f"rel_mpc{h0}_speedup_vs_conic": speedup,
        "bench": "mpc_speed",
        "scenario": sc.name,
        "model": model_desc,
        "params": n_params,
        "device": args.device,
        "problems": len(problems),
        "max_steps": args.max_steps,
        "results": results,
        f"ratio_rel30_over_{name.lower().replace('-', '_')}10": ratio,
        f"ratios_at_h{h0}": today,
        "episode_cost": cost,
        "dagger": dagger,
        **machine.record(),
    }
    write_result(summary, None if args.quick else args.out)


if __name__ == "__main__":
    main()
