"""``ttompc evaluate {warmstart,mpc}``: the open-loop warm-start evaluation (Fig. 3) and the closed-loop
planning-horizon study (Fig. 4–5), written as JSON + CSV + PNG into ``--out``."""

from __future__ import annotations

import argparse
import json


def _ints(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def _common(p: argparse.ArgumentParser, checkpoint_required: bool) -> None:
    p.add_argument(
        "--checkpoint",
        required=checkpoint_required,
        help="TTO model: Lightning checkpoint (.ckpt), planner bundle directory or zoo model name",
    )
    p.add_argument("--ft-checkpoint", help="fine-tuned (FT-TTO) model, same forms as --checkpoint")
    p.add_argument("--scenario", help="scenario name (default: the model's scenario)")
    p.add_argument("--problems", type=int, default=10, help="number of seeded held-out problems")
    p.add_argument("--seed", type=int, default=0, help="root seed of the evaluation problems")
    p.add_argument("--workers", type=int, default=1, help="processes (spawn pool; each loads the model once)")
    p.add_argument("--backend", default="auto", help="convex solver backend")
    p.add_argument("--device", default="cpu", help="torch device of the model(s)")
    p.add_argument("--out", required=True, help="output directory")


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="evaluation", metavar="EVALUATION", required=True)
    ws = sub.add_parser("warmstart", help="REL vs transformer warm starts of the open-loop SCP (Fig. 3)")
    _common(ws, checkpoint_required=True)
    ws.add_argument("--thresholds", default=None, help="non-convexity thresholds, e.g. 0,0.2,0.4 (default 0..0.9)")
    mpc = sub.add_parser("mpc", help="REL-/DIST-/TTO-/FT-TTO-MPC over planning horizons (Fig. 4-5)")
    _common(mpc, checkpoint_required=False)
    mpc.add_argument("--horizons", type=_ints, default=list(range(10, 101, 10)), help="e.g. 10,20,30")
    mpc.add_argument("--mode", choices=["soft", "hard"], default="soft")
    mpc.add_argument("--max-steps", type=int, default=None, help="truncate episodes (smoke runs)")


def _scenario(args: argparse.Namespace) -> str:
    if args.scenario:
        return args.scenario
    if not args.checkpoint:
        raise SystemExit("ttompc evaluate: --scenario is required without --checkpoint")
    from ttompc.policy import Planner

    return Planner.from_pretrained(args.checkpoint).scenario.name


def run(args: argparse.Namespace) -> int:
    scenario = _scenario(args)
    if args.evaluation == "warmstart":
        from ttompc.evaluation.warmstart import WarmStartConfig, run_warmstart

        cfg = WarmStartConfig(
            scenario=scenario,
            out=args.out,
            checkpoint=args.checkpoint,
            ft_checkpoint=args.ft_checkpoint,
            problems=args.problems,
            seed=args.seed,
            workers=args.workers,
            backend=args.backend,
            device=args.device,
        )
        if args.thresholds:
            cfg.thresholds = [float(v) for v in args.thresholds.split(",")]
        report = run_warmstart(cfg)
        print(json.dumps({"methods": report["methods"], "out": args.out}, indent=2))
        return 0
    from ttompc.evaluation.horizon import HorizonStudyConfig, run_horizon_study

    cfg_h = HorizonStudyConfig(
        scenario=scenario,
        out=args.out,
        checkpoint=args.checkpoint,
        ft_checkpoint=args.ft_checkpoint,
        horizons=args.horizons,
        problems=args.problems,
        seed=args.seed,
        workers=args.workers,
        mode=args.mode,
        max_steps=args.max_steps,
        backend=args.backend,
        device=args.device,
    )
    report = run_horizon_study(cfg_h)
    for r in report["summary"]:
        print(
            f"{r['method']:>11} H={r['horizon']:>3}  cost {r['cost']:.4g}  norm {r['norm_cost_increment']:.3f}  "
            f"feasible {r['feasible_rate']:.2f}  max step {r['max_step_time'] * 1e3:.1f} ms"
        )
    print(f"report: {args.out}/horizon.json")
    return 0
