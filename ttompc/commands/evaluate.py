"""``ttompc evaluate warmstart|mpc|target|loss [RECIPE.yaml] key=value ...``: the evaluation protocol
(docs/evaluation.md); ``ttompc evaluate compare BASE OTHER ...``: pair closed-loop reports made on the same problems.

* ``warmstart``: open-loop SCP warm starts, REL vs the model(s) vs the oracle (best of several warm starts), on
  ``problems`` (default 100) held-out non-convex problems (``WarmStartConfig`` keys);
* ``mpc``: closed loop, REL-/DIST-MPC, plan-once, the oracle, TTO-MPC and the robust R-TTO-MPC, on the nominal and
  the perturbed plant, ``problems`` (default 20) held-out non-convex problems (``ClosedLoopConfig`` keys), under
  ``protocol=paper|recommended|zoo|FILE.yaml`` with single settings overridden as ``mpc.KEY=VALUE``
  (``ttompc.mpc.settings``);
* ``target``: along the closed-loop episodes of one method, the distance of its terminal target and first control
  from the expert's re-solved from the measured state, by steps to go and plant, and its correlation with the
  closed-loop cost (``TargetErrorConfig`` keys; ``ttompc.evaluation.target_error``);
* ``loss``: a model's training objective on the splits of its datasets, open-loop and DAgger rows apart
  (``LossConfig`` keys; ``ttompc.training.fit_loss``);
* ``compare``: pairs ``mpc`` reports on their common problems (``ttompc.evaluation.compare``), prints a table and
  with ``--json FILE`` writes its rows.

Reports (JSON, a markdown table, CSV, PNG) go to ``out`` (default ``outputs/evaluate/<kind>-<scenario>``).
``--print-config`` of ``mpc`` shows the protocol's resolved settings too (``settings``: what ``protocol=zoo`` means).
``--model``, ``--ft-model``, ``--scenario``, ``--problems``, ``--seed``, ``--workers`` and ``--out`` are shortcuts
for the keys of the same name.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from ttompc.commands import checks
from ttompc.config import add_config_arguments, command_config, to_container
from ttompc.errors import UserError
from ttompc.progress import status

if TYPE_CHECKING:
    from ttompc.evaluation.closed_loop import ClosedLoopConfig
    from ttompc.evaluation.warmstart import WarmStartConfig
    from ttompc.policy import Planner

_FLAGS = ("model", "ft_model", "scenario", "problems", "seed", "workers", "out")  # shortcut flags, dest = config key


def _shortcuts(p: argparse.ArgumentParser, example: str, problems: int) -> None:
    add_config_arguments(p, example)
    p.add_argument("--model", help="TTO model: zoo name, hf://ORG/NAME[@REV], bundle folder or Lightning .ckpt")
    p.add_argument("--ft-model", dest="ft_model", help="fine-tuned (FT-TTO) model, same forms as --model")
    p.add_argument("--scenario", help="scenario (default: the model's)")
    p.add_argument("--problems", type=int, help=f"number of held-out non-convex problems (default {problems})")
    p.add_argument("--seed", type=int, help="root seed of the held-out evaluation stream (default 0)")
    p.add_argument("--workers", type=int, help="processes (default 0 = one per CPU core)")
    p.add_argument("--out", help="output folder (default outputs/evaluate/<kind>-<scenario>)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="evaluation", metavar="EVALUATION", required=True)
    ws = sub.add_parser("warmstart", help="open loop: SCP from REL vs from the model(s) vs the oracle")
    _shortcuts(ws, "problems=100 seed=2027 rtg_scale=1.3", 100)
    mpc = sub.add_parser("mpc", help="closed loop: REL/DIST/plan-once/oracle/TTO-MPC, nominal and perturbed plant")
    _shortcuts(mpc, "protocol=zoo horizons=[10,30] plants=[perturbed] plant.process_std=0.005", 20)
    target = sub.add_parser("target", help="closed loop: a method's target and first control vs the expert's")
    _shortcuts(target, "method=R-FT-TTO-MPC horizons=[10] every=2 plot=true", 20)
    loss = sub.add_parser("loss", help="training objective by split, open-loop and DAgger (closed-loop) rows apart")
    add_config_arguments(loss, "data.paths=[data/quadrotor-v4] data.dagger_dirs=[runs/ft/dagger/iter-000] rows=2000")
    loss.add_argument("--model", help="model: zoo name, hf://ORG/NAME[@REV], bundle folder or Lightning .ckpt")
    loss.add_argument("--out", help="output folder (default outputs/evaluate/loss-<model>)")
    cmp = sub.add_parser(
        "compare",
        help="pair closed-loop reports made on the same held-out problems: goals lost/won, paired cost, step time",
    )
    cmp.add_argument("base", metavar="BASE", help="report folder of `evaluate mpc` (or its mpc_runs.csv)")
    cmp.add_argument("others", metavar="OTHER", nargs="+", help="reports to pair against BASE, same forms")
    cmp.add_argument("--methods", help="only these methods, comma-separated (e.g. REL-MPC,TTO-MPC)")
    cmp.add_argument("--horizons", help="only these horizons, comma-separated (e.g. 10,30)")
    cmp.add_argument("--json", metavar="FILE", help="also write the rows to FILE as JSON")


def _resolve_scenario(cfg: WarmStartConfig | ClosedLoopConfig) -> None:
    """The scenario defaults to the model's; settings and models are checked before any work. Every model is loaded
    here as the pool workers will load it: a name that is not in the zoo, a damaged bundle or a model of another
    scenario is one error line before the pool starts, not a failure in every worker. The devices the settings name
    must exist here (``ttompc.ranges.check_devices``)."""
    from ttompc.evaluation.warmstart import WarmStartConfig
    from ttompc.ranges import check_devices

    check_devices(cfg)
    sources = [source for source in (cfg.model, cfg.ft_model) if source]
    if not sources:
        if cfg.scenario is None:
            raise UserError("evaluate needs a model or a scenario", "pass --model NAME or scenario=NAME")
        checks.scenario(cfg.scenario)
    else:
        from ttompc.policy import Planner

        if cfg.scenario is None:
            cfg.scenario = Planner.from_pretrained(sources[0]).scenario.name
        scenario = checks.scenario(cfg.scenario)
        for source in sources:
            planner = Planner.from_pretrained(source, scenario, device=cfg.device)
            if not isinstance(cfg, WarmStartConfig):
                _announce_rtg(source, planner, cfg.settings.rtg_mode)
    checks.backend(cfg.backend if isinstance(cfg, WarmStartConfig) else cfg.settings.backend)


def _announce_rtg(source: str, planner: Planner, mode: str) -> None:
    """Say so when ``planner`` runs another rtg mode than the settings name (``ttompc.mpc.rtg``: a model without a
    value output runs the paper's ledger under ``value``), whose methods the report names without the mode."""
    from ttompc.mpc.rtg import RTG_MODES, rtg_feed

    runs = rtg_feed(mode, planner).name
    if runs != mode:
        status(
            f"ttompc evaluate mpc: {source} has no value output, which rtg_mode={mode} reads: its methods run "
            f"rtg_mode={runs} (named without {RTG_MODES[mode].label()})"
        )


def _announce(kind: str, cfg: WarmStartConfig | ClosedLoopConfig) -> None:
    """Loading the models and starting the workers takes a while before the progress bar appears: say so at once."""
    models = " and ".join(source for source in (cfg.model, cfg.ft_model) if source) or "no model (baselines only)"
    status(f"ttompc evaluate {kind}: {cfg.problems} problems; loading {models}")


def _compare(args: argparse.Namespace) -> int:
    """``evaluate compare``: the pairing and its table live in ``ttompc.evaluation.compare`` (no solver, no torch)."""
    from ttompc.evaluation.compare import compare_reports, format_comparison
    from ttompc.evaluation.metrics import write_json

    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None
    horizons = None
    if args.horizons:
        try:
            horizons = [int(h) for h in args.horizons.split(",") if h.strip()]
        except ValueError:
            raise UserError(f"--horizons {args.horizons} is not a list of integers", "e.g. --horizons 10,30") from None
    rows = compare_reports(args.base, args.others, methods=methods, horizons=horizons)
    print(format_comparison(rows))
    if args.json:
        write_json(args.json, rows)
    return 0


def _measured(kind: str, config_cls: Any, runner: Callable[[Any], dict[str, Any]], args: argparse.Namespace) -> int:
    """``evaluate mpc`` and ``evaluate target``: a closed-loop measurement, checked alike (models, scenario,
    settings; the runner claims its output folder before any work, ``report_files.claim_report``);
    ``--print-config`` shows the protocol's resolved settings."""
    from ttompc.evaluation.measurement import with_settings

    cfg = command_config(config_cls, args, _FLAGS)
    if args.print_config:
        print(json.dumps(with_settings(cfg), indent=2))
        return 0
    _announce(kind, cfg)
    _resolve_scenario(cfg)
    report = runner(cfg)
    print(report["table"])
    print(f"report: {report['out']}")
    return 0


def _loss(args: argparse.Namespace) -> int:
    """``evaluate loss``: the device and then, in ``run_fit_loss``, the output folder (new, empty or a loss
    report's) are checked before the model and the data are read."""
    from ttompc.ranges import check_devices
    from ttompc.training.fit_loss import LossConfig, run_fit_loss

    cfg = command_config(LossConfig, args, ("model", "out"))
    if args.print_config:
        print(json.dumps(to_container(cfg), indent=2))
        return 0
    check_devices(cfg)
    report = run_fit_loss(cfg)
    print(report["table"])
    print(f"report: {report['out']}")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.evaluation == "compare":
        return _compare(args)
    if args.evaluation == "warmstart":
        from ttompc.evaluation.warmstart import WarmStartConfig, run_warmstart

        cfg = command_config(WarmStartConfig, args, _FLAGS)
        if args.print_config:
            print(json.dumps(to_container(cfg), indent=2))
            return 0
        if not cfg.model and not cfg.ft_model:
            raise UserError(
                "evaluate warmstart needs a model", "pass --model NAME (zoo name, hf://ORG/NAME, folder or .ckpt)"
            )
        _announce("warmstart", cfg)
        _resolve_scenario(cfg)
        report = run_warmstart(cfg)
    elif args.evaluation == "target":
        from ttompc.evaluation.target_error import TargetErrorConfig, run_target_error

        return _measured("target", TargetErrorConfig, run_target_error, args)
    elif args.evaluation == "loss":
        return _loss(args)
    else:
        from ttompc.evaluation.closed_loop import ClosedLoopConfig, run_closed_loop

        return _measured("mpc", ClosedLoopConfig, run_closed_loop, args)
    print(report["table"])
    print(f"report: {report['out']}")
    return 0
