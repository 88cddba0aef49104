"""``ttompc check-scenario SPEC [key=value ...]``: check a scenario against the contract the engine, the datasets,
the rollout and MPC rely on (``ttompc.scenario_check``), one line per check, before generating data with it.

SPEC is any scenario spec: a name, ``module:Class``, ``path/to/file.py:Class`` or an entry point. Settings are
``CheckConfig`` keys (``problems``, ``seed``, ``backend``). Exit status 0 when every check passes, 1 otherwise; a
spec that names no scenario is a one-line error (exit 2)."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass

from ttompc.commands import checks
from ttompc.config import command_config, to_container
from ttompc.errors import UserError
from ttompc.ranges import Checked, setting


@dataclass
class CheckConfig(Checked):
    scenario: str = "???"  # the positional SPEC
    problems: int = setting(3, ge=1)  # sampled problems the checks use (and solve)
    seed: int = setting(0, ge=0)  # root seed: problem i is drawn as ``ttompc generate`` draws it
    backend: str = "auto"  # convex backend of the solve check


_FLAGS = {"spec": "scenario", "problems": "problems", "seed": "seed", "backend": "backend"}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", metavar="SPEC", help="scenario: name, module:Class, path/to/file.py:Class, entry point")
    p.add_argument("settings", nargs="*", metavar="key=value", help="CheckConfig overrides, e.g. problems=5")
    p.add_argument("--problems", type=int, help="sampled problems to check and solve (default 3)")
    p.add_argument("--seed", type=int, help="root seed of the sampled problems (default 0)")
    p.add_argument("--backend", help="auto|conic|riccati|piqp|clarabel|qoco|cvxpy-naive (default auto)")
    p.add_argument("--print-config", action="store_true", help="print the resolved config as JSON and exit")


def run(args: argparse.Namespace) -> int:
    cfg = command_config(CheckConfig, args, _FLAGS)
    if args.print_config:
        print(json.dumps(to_container(cfg), indent=2))
        return 0
    checks.backend(cfg.backend)
    if cfg.problems < 1:
        raise UserError(f"problems must be at least 1, got {cfg.problems}")
    scenario = checks.scenario(cfg.scenario)
    from ttompc.scenario_check import check_scenario
    from ttompc.scenarios import scenario_spec

    print(f"{scenario.name} v{scenario.version} ({scenario_spec(scenario)}), {cfg.problems} problems, seed {cfg.seed}")
    findings = []
    for finding in check_scenario(scenario, problems=cfg.problems, seed=cfg.seed, backend=cfg.backend):
        print(finding, flush=True)
        findings.append(finding)
    failed = [f.check for f in findings if not f.ok]
    print(f"{len(failed)} of {len(findings)} checks failed: {', '.join(failed)}" if failed else "all checks passed")
    return 1 if failed else 0
