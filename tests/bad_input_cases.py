"""The tables of ``tests/test_bad_input.py``: bad input as a user types it (issue 58's cases, generated ones, paths)
and the folders they point at (``make_world``); the Python entries behind the commands are ``bad_input_api``'s."""

from __future__ import annotations

import json
import typing
from dataclasses import asdict, fields, is_dataclass
from pathlib import Path
from typing import Any

from cli_batch import read_only_folder

from ttompc.commands.check_scenario import CheckConfig
from ttompc.commands.demo import DemoConfig
from ttompc.commands.solve import SolveConfig
from ttompc.data.config import GenerateConfig
from ttompc.evaluation.closed_loop import ClosedLoopConfig
from ttompc.evaluation.warmstart import WarmStartConfig
from ttompc.finetune.config import FinetuneConfig
from ttompc.mpc.settings import MPCSettings
from ttompc.ranges import ALLOWED, Allowed
from ttompc.training.config import TrainConfig

REPO = Path(__file__).resolve().parents[1]
TINY = str(REPO / "recipes/freeflyer/tiny.yaml")
QUAD_TINY = str(REPO / "recipes/quadrotor/tiny.yaml")
BUNDLE = str(REPO / "zoo/models/freeflyer-tto-small")  # a model that loads offline
FINETUNE = str(REPO / "recipes/freeflyer/finetune.yaml")
SMALL_SPLITS = ["problems=2", "splits.train=1", "splits.val=0", "splits.test=0"]
# the command line of each schema, up to its settings
SCHEMAS: dict[str, tuple[type, list[str]]] = {
    "solve": (SolveConfig, ["solve"]),
    "generate": (GenerateConfig, ["generate"]),
    "train": (TrainConfig, ["train", TINY]),
    "finetune": (FinetuneConfig, ["finetune", FINETUNE]),
    "evaluate mpc": (ClosedLoopConfig, ["evaluate", "mpc"]),
    "evaluate warmstart": (WarmStartConfig, ["evaluate", "warmstart"]),
    "demo": (DemoConfig, ["demo"]),
    "check-scenario": (CheckConfig, ["check-scenario", "freeflyer"]),
}
HUGE = {int: 10**12, float: 1e300}
MILLION = "1000000"  # processes beyond any machine's cores (4 per core: ``ttompc.ranges``), a horizon beyond any N


# (id, argv, what the line must say); {name} is a path of the fixture ``world``
LISTED: list[tuple[str, list[str], list[str]]] = [
    # a wrong model, silently: free-flyer weights resumed on quadrotor data; another architecture's checkpoints
    (
        "train-resumes-another-scenario",
        ["train", QUAD_TINY, "data.paths=[{quad}]", "trainer.out_dir={ff_run}"],
        ["holds checkpoints of another run", "scenario freeflyer there, quadrotor here", "trainer.resume=false"],
    ),
    (
        "train-resumes-another-architecture",
        ["train", TINY, "data.paths=[{ff}]", "trainer.out_dir={wide_run}"],
        ["holds checkpoints of another run", "model.n_embd=512 there"],
    ),
    (
        "train-into-a-users-folder",
        ["train", TINY, "data.paths=[{ff}]", "trainer.out_dir={user}"],
        ["{user} holds files that `ttompc train` did not write (README.md, manifest.json)"],
    ),
    (
        "finetune-into-a-users-folder",
        ["finetune", FINETUNE, "--model", "m", "data.paths=[{ff}]", "trainer.out_dir={user}"],
        ["{user} holds files that `ttompc finetune` did not write"],
    ),
    # data loss: generate into a user's folder, or into an evaluation report
    (
        "generate-into-a-users-folder",
        ["generate", *SMALL_SPLITS, "out={user}"],
        ["{user} holds files that `ttompc generate` did not write (README.md, manifest.json)"],
    ),
    (
        "generate-into-a-report",
        ["generate", *SMALL_SPLITS, "out={report}"],
        ["holds files that `ttompc generate` did not write", "mpc.json"],
    ),
    (
        "mpc-max-steps-0",
        ["evaluate", "mpc", "--scenario", "freeflyer", "max_steps=0"],
        ["invalid max_steps=0: must be >= 1"],
    ),
    (
        "mpc-max-steps-negative",
        ["evaluate", "mpc", "--scenario", "freeflyer", "max_steps=-1"],
        ["invalid max_steps=-1: must be >= 1"],
    ),
    # damaged manifests
    (
        "train-truncated-manifest",
        ["train", TINY, "data.paths=[{truncated}]", "trainer.out_dir=run"],
        ["manifest.json is damaged (not JSON"],
    ),
    (
        "train-manifest-without-scenario",
        ["train", TINY, "data.paths=[{no_scenario}]", "trainer.out_dir=run"],
        ["manifest.json is incomplete: it names no scenario"],
    ),
    (
        "finetune-truncated-manifest",
        ["finetune", FINETUNE, "--model", "m", "data.paths=[{truncated}]"],
        ["manifest.json is damaged (not JSON"],
    ),
    (
        "finetune-manifest-without-scenario",
        ["finetune", FINETUNE, "--model", "m", "data.paths=[{no_scenario}]"],
        ["manifest.json is incomplete"],
    ),
    # an unbalanced bracket in key=value, in every command
    *[
        (
            f"unbalanced-bracket-{'-'.join(argv[:2])}",
            [*argv, "seed=[10,"],
            ["cannot parse seed=[10,: its value is not valid YAML"],
        )
        for argv in (
            ["solve"],
            ["generate"],
            ["train", TINY],
            ["finetune", FINETUNE],
            ["evaluate", "mpc"],
            ["evaluate", "warmstart"],
            ["demo"],
            ["check-scenario", "freeflyer"],
        )
    ],
    ("recipe-with-unbalanced-bracket", ["generate", "{bad_yaml}"], ["is not valid YAML", "at line 3"]),
    ("recipe-that-is-a-list", ["generate", "{list_yaml}"], ["holds a YAML list, not settings"]),
    ("recipe-that-is-a-folder", ["generate", "{user}"], ["is a folder"]),
    (
        "splits-that-do-not-sum-to-1",
        ["generate", "splits.val=0", "splits.test=0", "out=o"],
        ["invalid splits: train + val + test must sum to 1, got 0.9 + 0 + 0 = 0.9"],
    ),
    (
        "splits-flag-that-does-not-sum-to-1",
        ["generate", "--splits", "0.5,0.5,0.5", "out=o"],
        ["must sum to 1", "= 1.5"],
    ),
    ("trainer-max-steps-0", ["train", TINY, "trainer.max_steps=0"], ["invalid trainer.max_steps=0: must be >= 1"]),
    ("trainer-max-steps-endless", ["train", TINY, "trainer.max_steps=-1"], ["trainer.max_epochs, which is null"]),
    ("batch-size-0", ["train", TINY, "data.batch_size=0"], ["invalid data.batch_size=0: must be >= 1"]),
    (
        "model-shorter-than-the-data",
        ["train", TINY, "data.paths=[{ff}]", "model.max_steps=10", "trainer.out_dir=r"],
        ["invalid model.max_steps=10", "100-step trajectories"],
    ),
    ("trainer-devices-0", ["train", TINY, "trainer.devices=0"], ["invalid trainer.devices=0"]),
    (
        "limit-val-batches-between-batch-counts",
        ["train", TINY, "trainer.limit_val_batches=1.5"],
        ["invalid trainer.limit_val_batches=1.5", "a whole number of batches"],
    ),
    (
        "val-check-interval-0",
        ["train", TINY, "trainer.val_check_interval=0"],
        ["invalid trainer.val_check_interval=0.0: must be > 0"],
    ),
    ("solve-plot-unknown-format", ["solve", "--plot", "x.xyz"], [".xyz is not an image format", ".png"]),
    ("solve-plot-folder", ["solve", "--plot", "{user}"], ["is a folder", "plot.png"]),
    (
        "mpc-plants-repeated",
        ["evaluate", "mpc", "--scenario", "freeflyer", "plants=[nominal,nominal]"],
        ["invalid plants=", "without repeats"],
    ),
    (
        "mpc-workers-negative",
        ["evaluate", "mpc", "--scenario", "freeflyer", "workers=-1"],
        ["invalid workers=-1: must be >= 0"],
    ),
    ("generate-workers-negative", ["generate", "workers=-1"], ["invalid workers=-1: must be >= 0"]),
    (
        "warmstart-thresholds-empty",
        ["evaluate", "warmstart", "--model", "m", "thresholds=[]"],
        ["invalid thresholds=[]: must be a non-empty list"],
    ),
    (
        "warmstart-thresholds-negative",
        ["evaluate", "warmstart", "--model", "m", "thresholds=[2,-1]"],
        ["invalid thresholds=", "each >= 0"],
    ),
    (
        "dagger-horizon-beyond-the-data",
        ["finetune", FINETUNE, "--model", "m", "data.paths=[{ff}]", "dagger.exploration.horizons=[500]"],
        ["invalid dagger.exploration.horizons=[500]", "100 steps"],
    ),
    ("generate-max-shards-0", ["generate", "max_shards=0"], ["invalid max_shards=0: must be >= 1"]),
    ("zoo-that-does-not-exist", ["zoo", "list"], ["no zoo at", "$TTOMPC_ZOO does not exist"]),
    (
        "mpc-device-that-does-not-exist",
        ["evaluate", "mpc", "--scenario", "freeflyer", "device=nosuch"],
        ['invalid device="nosuch": must be a device of this machine'],
    ),
    # huge values: beyond the integers' bound, the machine's cores (4 per core), the scenario's N
    (
        "generate-problems-huge",
        ["generate", "problems=1000000000000"],
        ["invalid problems=1000000000000: must be in [1, 2147483647]"],
    ),
    (
        "generate-workers-beyond-the-machine",
        ["generate", *SMALL_SPLITS, f"workers={MILLION}", "out=o"],
        [f"invalid workers={MILLION}: must be at most", "on this machine (4 per CPU core)"],
    ),
    (
        "mpc-workers-beyond-the-machine",
        ["evaluate", "mpc", "--scenario", "freeflyer", f"workers={MILLION}"],
        [f"invalid workers={MILLION}: must be at most"],
    ),
    (
        "warmstart-workers-beyond-the-machine",
        ["evaluate", "warmstart", "--model", "m", f"workers={MILLION}"],
        [f"invalid workers={MILLION}: must be at most"],
    ),
    (
        "finetune-workers-beyond-the-machine",
        ["finetune", FINETUNE, "--model", "m", "data.paths=[{ff}]", f"dagger.collect.workers={MILLION}"],
        [f"invalid dagger.collect.workers={MILLION}: must be at most"],
    ),
    (
        "train-loader-workers-beyond-the-machine",
        ["train", TINY, "data.paths=[{ff}]", f"data.num_workers={MILLION}", "trainer.out_dir=r"],
        [f"invalid data.num_workers={MILLION}"],
    ),
    (
        "train-devices-beyond-the-machine",
        ["train", TINY, "data.paths=[{ff}]", f"trainer.devices={MILLION}", "trainer.out_dir=r"],
        [f"invalid trainer.devices={MILLION}: must be at"],
    ),
    (
        "mpc-horizon-beyond-N",
        ["evaluate", "mpc", "--scenario", "freeflyer", f"horizons=[{MILLION}]"],
        [f"horizons [{MILLION}] exceed the horizon of freeflyer, N = 100 steps"],
    ),
    (
        "demo-horizon-beyond-N",
        ["demo", "--horizon", MILLION, "out=o"],
        [f"horizon {MILLION} exceeds the horizon of freeflyer, N = 100 steps"],
    ),
    # output folders: only new, empty or the command's own; a report of another configuration is not replaced
    ("demo-into-a-users-folder", ["demo", "--no-mpc", "out={user}"], ["{user} holds files that `ttompc demo` did not"]),
    *[  # the library calls claim their folder too (``bad_input_api``)
        (
            f"{kind}-into-a-users-folder",
            ["evaluate", kind, *source, "out={user}"],
            ["{user} holds files that `ttompc evaluate " + kind + "` did not write (README.md, manifest.json)"],
        )
        for kind, source in (
            ("mpc", ["--scenario", "freeflyer", "problems=1"]),
            ("warmstart", ["--model", BUNDLE, "problems=1"]),
            ("target", ["--model", BUNDLE, "problems=1"]),
            ("loss", ["--model", BUNDLE]),
        )
    ],
    (
        "publish-into-a-users-folder",
        ["zoo", "publish", BUNDLE, "--name", "x", "--to", "{user}"],
        ["{user} holds files that `ttompc zoo publish` did not write (README.md, manifest.json)"],
    ),
    (
        "warmstart-over-another-configuration",
        ["evaluate", "warmstart", "--model", BUNDLE, "problems=1", "out={ws_report}"],
        ["{ws_report} holds a `ttompc evaluate warmstart` report of another configuration (problems: 1 here, 2 there)"],
    ),
    # the Python entries say the same (``test_the_python_entries_refuse_in_the_clis_words``)
    ("solve-unknown-scenario", ["solve", "scenario=nosuch"], ["unknown scenario 'nosuch'"]),
    ("solve-unknown-backend", ["solve", "backend=nosuch"], ["unknown solver backend 'nosuch'; choose one of: auto"]),
    (
        "mpc-device-cuda-without-a-gpu",
        ["evaluate", "mpc", "--scenario", "freeflyer", "device=cuda"],
        ['invalid device="cuda"'],
    ),
    (
        "train-accelerator-gpu-without-a-gpu",
        ["train", TINY, "trainer.accelerator=gpu"],
        ['invalid trainer.accelerator="gpu": must be an accelerator of this machine'],
    ),
]
NEEDS_NO_GPU = {"mpc-device-cuda-without-a-gpu", "train-accelerator-gpu-without-a-gpu"}
ENV = {"zoo-that-does-not-exist": {"TTOMPC_ZOO": "{missing}"}}


def settings_of(schema: type, prefix: str = "") -> list[tuple[str, type, Allowed | None]]:
    """(dotted key, value type, declared range) of every numeric or list setting of ``schema``, nested sections and
    a measurement's ``mpc`` overrides (``MPCSettings``) included; a list of numbers is typed by its items' type, as
    ``list[int]``."""
    out: list[tuple[str, Any, Allowed | None]] = []
    hints = typing.get_type_hints(schema)
    for f in fields(schema):
        hint = hints[f.name]
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        base = typing.get_origin(hint) or hint
        if f.name == "mpc" and base is dict:
            out += settings_of(MPCSettings, f"{prefix}mpc.")
        elif is_dataclass(hint):
            out += settings_of(hint, f"{prefix}{f.name}.")  # type: ignore[arg-type]
        elif base is list or (len(args) == 1 and args[0] in (int, float)) or hint in (int, float):
            items = [a for a in typing.get_args(hint) if a in (int, float)]
            numbers: Any = {int: list[int], float: list[float]}.get(items[0]) if items else list
            kind = numbers if base is list else (args[0] if args else hint)
            out.append((f"{prefix}{f.name}", kind, f.metadata.get(ALLOWED)))
    return out


def generated_cases() -> list[tuple[str, list[str], str, Any, Allowed | None]]:
    """(id, argv, key, value, declared range): every numeric setting at 0, -1 and huge, every list empty and a list
    of numbers of one huge item; a float setting with an upper bound (a fraction, a blend) also just above it."""
    cases = []
    for cmd, (schema, argv) in SCHEMAS.items():
        for key, kind, allowed in settings_of(schema):
            item = typing.get_args(kind)[0] if typing.get_origin(kind) is list else None
            values = [[]] if kind is list else [[], [HUGE[item]]] if item else [kind(0), kind(-1), HUGE[kind]]
            top = None if allowed is None else allowed.le if allowed.le is not None else allowed.lt
            if float in (kind, item) and top is not None:
                values.append([top + 0.5] if item else top + 0.5)
            for value in values:
                shown = json.dumps(value)
                cases.append((f"{cmd} {key}={shown}", [*argv, f"{key}={shown}", "--print-config"], key, value, allowed))
    return cases


def path_cases() -> list[tuple[str, list[str], list[str]]]:
    """Every path a command reads (missing, a file) or writes into (a file in the way, a read-only folder)."""
    cases = []
    # a recipe that is a file is a recipe (an empty file: no settings), so only a missing one
    cases.append(("recipe-missing", ["generate", "{missing}"], ["recipe not found"]))
    for what, bad, said in (("missing", "{missing}", "does not exist"), ("a-file", "{a_file}", "is a file")):
        cases += [
            (f"data-paths-{what}", ["train", TINY, f"data.paths=[{bad}]", "trainer.out_dir=r"], ["data.paths", said]),
            (
                f"finetune-data-{what}",
                ["finetune", FINETUNE, "--model", BUNDLE, f"data.paths=[{bad}]"],
                ["data.paths", said],
            ),
            (f"mpc-model-{what}", ["evaluate", "mpc", "--model", bad, "problems=1"], [bad]),
            (f"warmstart-model-{what}", ["evaluate", "warmstart", "--model", bad, "problems=1"], [bad]),
            (f"demo-model-{what}", ["demo", "--model", bad, "--no-mpc"], [bad]),
        ]
    for what, parent in (("under-a-file", "{a_file}"), ("in-a-read-only-folder", "{read_only}")):
        out = f"{parent}/out"
        cases += [
            (f"generate-out-{what}", ["generate", *SMALL_SPLITS, f"out={out}"], [f"cannot use {parent}"]),
            (
                f"train-out-{what}",
                ["train", TINY, "data.paths=[{ff}]", f"trainer.out_dir={out}"],
                [f"cannot use {parent}"],
            ),
            (f"mpc-out-{what}", ["evaluate", "mpc", "--scenario", "freeflyer", f"out={out}"], [f"cannot use {parent}"]),
            (f"demo-out-{what}", ["demo", "--no-mpc", f"out={out}"], [f"cannot use {parent}"]),
            (
                f"finetune-out-{what}",
                ["finetune", FINETUNE, "--model", "m", "data.paths=[{ff}]", f"trainer.out_dir={out}"],
                [f"cannot use {parent}"],
            ),
            (f"solve-plot-{what}", ["solve", "--plot", f"{out}.png"], [f"cannot use {parent}"]),
        ]
    return cases


def _manifest(scenario: str) -> dict[str, Any]:
    """What the checks before any work read of a dataset (``ttompc.data.manifests``): no shard is opened."""
    dims = {"n_steps": 100, "state_dim": 6, "control_dim": 3}
    return {"scenario": {"name": scenario, **dims}, "shards": [{"index": 0, "files": {"train": scenario}}]}


def make_world(root: Path) -> dict[str, str]:
    """Folders the cases point at: fake datasets (manifests only), a user's folder, a report, runs of another
    scenario and architecture, damaged manifests, bad recipes, a file and a read-only folder."""
    from ttompc.training.config import load_train_config
    from ttompc.training.preflight import run_identity

    paths: dict[str, Path] = {}
    for name, scenario in (("ff", "freeflyer"), ("quad", "quadrotor")):
        paths[name] = root / f"{name}-data"
        paths[name].mkdir()
        (paths[name] / "manifest.json").write_text(json.dumps(_manifest(scenario)))
    for name, text in (("truncated", '{"scenario": {"na'), ("no_scenario", '{"counts": {}}')):
        paths[name] = root / f"{name}-data"
        paths[name].mkdir()
        (paths[name] / "manifest.json").write_text(text)
    paths["user"] = root / "user-folder"
    paths["user"].mkdir()
    (paths["user"] / "README.md").write_text("# my notes\n")
    (paths["user"] / "manifest.json").write_text('{"mine": true}\n')
    paths["report"] = root / "report"
    paths["report"].mkdir()
    for name in ("mpc.json", "mpc.md", "mpc_runs.csv"):
        (paths["report"] / name).write_text("{}\n")
    ff = load_train_config(TINY, [f"data.paths=[{paths['ff']}]"])
    identity = run_identity(ff, [_manifest("freeflyer")])
    wide = {**identity, "architecture": {**identity["architecture"], "n_embd": 512}}
    for name, stored in (("ff_run", identity), ("wide_run", wide)):
        paths[name] = root / name
        (paths[name] / "checkpoints").mkdir(parents=True)
        (paths[name] / "checkpoints" / "last.ckpt").write_bytes(b"")
        (paths[name] / "run.json").write_text(json.dumps(stored))
    paths["ws_report"] = root / "warmstart-report"  # a complete report of problems=2 (``report_files.finish``)
    paths["ws_report"].mkdir()
    stored = {**asdict(WarmStartConfig(model=BUNDLE, scenario="freeflyer", problems=2)), "workers": 1}
    report = {"config": {**stored, "out": str(paths["ws_report"])}, "complete": True}
    (paths["ws_report"] / "warmstart.json").write_text(json.dumps(report))
    paths["bad_yaml"] = root / "bad.yaml"
    paths["bad_yaml"].write_text("problems: 3\nsplits: [1,\n")
    paths["list_yaml"] = root / "list.yaml"
    paths["list_yaml"].write_text("- problems\n- 3\n")
    paths["a_file"] = root / "a-file"
    paths["a_file"].write_text("")
    paths["missing"] = root / "no-such-thing"
    read_only = read_only_folder(root)
    paths["read_only"] = read_only if read_only is not None else root / "unused"
    out = {k: str(v) for k, v in paths.items()}
    out["root"], out["has_read_only"] = str(root), str(read_only is not None)
    return out
