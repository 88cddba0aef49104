"""Every YAML under recipes/ loads through its command's config loader (``ttompc train`` or ``ttompc finetune``),
holds no absolute path, and describes the run it claims to: its scenario's data, dimensions and output folder, the
architecture of the zoo model it produced, and (fine-tuning) the same open-loop dataset as the model it starts from.

Layout (one recipe per job): ``recipes/<scenario>/`` and ``recipes/generic/`` hold exactly ``pretrain``, ``finetune``,
``value`` and ``tiny`` (``generic/`` also ``first-look``, the measured quick path), and each ``recipes/<scenario>/``
also ``paper-{pretrain,finetune}.yaml``, the paper-size GPU recipes; ``recipes/zoo/<model>[-legN].yaml`` reproduce
published models, each headed by the ``ttompc generate`` command of its data. Every recipe path named in the cards,
README, docs, scripts and code exists."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from omegaconf import OmegaConf

from ttompc.config import ConfigError, to_container
from ttompc.finetune.config import FinetuneConfig, load_finetune_config
from ttompc.policy import TrajectoryGPT
from ttompc.policy.config import ModelConfig
from ttompc.scenarios import get_scenario
from ttompc.training.config import OptimConfig, TrainConfig, load_train_config

ROOT = Path(__file__).resolve().parents[1]
RECIPES = ROOT / "recipes"
ALL = sorted(RECIPES.glob("**/*.y*ml"))
SCENARIOS = ("freeflyer", "quadrotor", "rpod")
GENERIC = [p for p in ALL if p.parent.name == "generic"]
SCENARIO_RECIPES = [p for p in ALL if p not in GENERIC]
ARCHITECTURE = ("state_dim", "control_dim", "n_embd", "n_layer", "n_head", "mlp_ratio", "activation", "max_steps")
JOBS = {"pretrain", "finetune", "tiny", "value"}
PAPER_JOBS = {"paper-pretrain", "paper-finetune"}  # recipes/<scenario>/ only: the paper-size GPU recipes


def rel(path: Path) -> str:
    return path.relative_to(RECIPES).as_posix()


def is_paper(path: Path) -> bool:
    return path.stem in PAPER_JOBS


def is_finetune(path: Path) -> bool:
    """A fine-tuning recipe has a ``dagger`` section (a FT model's value output is added by a training recipe)."""
    return "dagger" in (yaml.safe_load(path.read_text()) or {})


def scenario_of(path: Path) -> str:
    """recipes/<scenario>/X.yaml, recipes/zoo/<scenario>-..."""
    return path.parent.name if path.parent.name in SCENARIOS else path.stem.split("-")[0]


def zoo_model(path: Path) -> str:
    """The published model a recipes/zoo/ file reproduces (a leg suffix names one of its training legs)."""
    return re.sub(r"-leg\d+$", "", path.stem)


def load(path: Path, overrides: list[str] | None = None) -> TrainConfig | FinetuneConfig:
    loader = load_finetune_config if is_finetune(path) else load_train_config
    return loader(path, overrides or [])


def source_recipe(path: Path) -> Path:
    """The training recipe of the model a fine-tuning recipe starts from."""
    if path.parent.name == "zoo":  # <s>-ft-tto-small -> <s>-tto-small; the v4+ FT models start from <s>-tto-v3
        small = path.with_name(path.name.replace("-ft-tto-", "-tto-"))
        return small if small.is_file() else RECIPES / scenario_of(path) / f"pretrain{path.suffix}"
    if is_paper(path):
        return path.with_name(f"paper-pretrain{path.suffix}")
    return path.with_name(f"pretrain{path.suffix}")


def leaves(node: Any) -> list[Any]:
    if isinstance(node, dict):
        return [x for v in node.values() for x in leaves(v)]
    if isinstance(node, list):
        return [x for v in node for x in leaves(v)]
    return [node]


def test_one_recipe_per_job() -> None:
    folders = {p.parent.name for p in ALL}
    assert folders == {*SCENARIOS, "generic", "zoo"}, "recipes live in recipes/<scenario>/, generic/ and zoo/"
    assert all(p.parent.parent == RECIPES for p in ALL)
    for folder in SCENARIOS:
        assert {p.stem for p in ALL if p.parent.name == folder} == JOBS | PAPER_JOBS, folder
    assert {p.stem for p in ALL if p.parent.name == "generic"} == JOBS | {"first-look"}  # the measured quick path
    published = {p.stem for p in (ROOT / "zoo").glob("*.md") if p.stem != "README"}
    for path in (p for p in ALL if p.parent.name == "zoo"):
        # a published model, or a withdrawn FT model of one (kept to repeat the rows measured with it)
        model = zoo_model(path)
        assert model in published or model.replace("-ft-tto-", "-tto-") in published, path.name
        command = next(line for line in path.read_text().splitlines() if line.lstrip("# ").startswith("ttompc "))
        assert command.lstrip("# ").startswith(f"ttompc generate --scenario {scenario_of(path)} "), path.name


@pytest.mark.parametrize("path", ALL, ids=rel)
def test_recipe_holds_no_absolute_path(path: Path) -> None:
    """Data and output folders are relative to where the command runs (or required on the command line); a machine's
    folder (/root/..., ~/...) in a recipe works only on that machine, in a value or in a command of its header."""
    values = leaves(OmegaConf.to_container(OmegaConf.load(path)))
    absolute = [v for v in values if isinstance(v, str) and (Path(v).is_absolute() or v.startswith("~"))]
    assert not absolute, f"{path.name}: {absolute}"
    in_text = re.findall(r"(?:^|[\s=\[,'\"])((?:~[/A-Za-z]|/[A-Za-z])\S*)", path.read_text())
    assert not in_text, f"{path.name}: {in_text}"


def test_the_absolute_path_check_can_fail(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("data:\n  paths: [/root/data/freeflyer-v3]\n")
    with pytest.raises(AssertionError, match="/root/data"):
        test_recipe_holds_no_absolute_path(bad)


@pytest.mark.parametrize("path", SCENARIO_RECIPES, ids=rel)
def test_recipe_loads_and_matches_its_scenario(path: Path) -> None:
    cfg = load(path)
    scenario = get_scenario(scenario_of(path))
    assert cfg.data.paths, "a scenario recipe names its dataset (relative to where the command runs)"
    # every scenario recipe names its scenario, checked against every dataset's manifest before training
    assert cfg.data.scenario == scenario.name
    for data in cfg.data.paths:
        assert Path(data).name.startswith(f"{scenario.name}-"), f"{data} is not a {scenario.name} dataset"
    assert scenario.name in Path(cfg.trainer.out_dir).name
    if isinstance(cfg, TrainConfig):
        model = cfg.model
        assert (model.state_dim, model.control_dim) == (scenario.state_dim, scenario.control_dim)
        assert (cfg.data.context_length or scenario.n_steps) <= model.max_steps
        assert scenario.n_steps <= model.max_steps, "the model must cover a full-horizon rollout"
    else:
        assert all(h <= scenario.n_steps for h in cfg.dagger.exploration.horizons)


@pytest.mark.parametrize("path", [p for p in ALL if not is_finetune(p)], ids=rel)
def test_training_recipe_builds_the_model_it_describes(path: Path) -> None:
    cfg = load_train_config(path)
    n_params = TrajectoryGPT(cfg.model).num_parameters()
    folder = path.parent.name
    if is_paper(path):  # the paper's size
        assert (cfg.model.n_embd, cfg.model.n_layer, cfg.model.n_head) == (384, 6, 6)
        assert cfg.optim.accumulate == 8 and cfg.optim.grad_clip == 1.0
        assert 10.5e6 < n_params < 11.5e6
    elif path.stem == "tiny":
        assert n_params < 300_000
    else:  # the zoo model it trained: pretrain.yaml the current one (-tto-v3), recipes/zoo/ the one it names,
        # first-look.yaml the -tto-small architecture (interleaved)
        model = zoo_model(path) if folder == "zoo" else f"{'freeflyer' if folder == 'generic' else folder}-tto-v3"
        model = "freeflyer-tto-small" if path.stem == "first-look" else model
        bundle: dict[str, Any] = json.loads((ROOT / "zoo" / "models" / model / "config.json").read_text())
        keys = ARCHITECTURE[2:-1] if folder == "generic" else ARCHITECTURE  # generic: dims and horizon follow data
        assert {k: getattr(cfg.model, k) for k in keys} == {k: bundle["model"][k] for k in keys}
        assert cfg.model.layout == bundle["model"].get("layout", "interleaved")
    if re.search(r"-leg\d+$", path.stem):
        assert cfg.init_from, "a continuation leg starts from the previous leg's weights"


LEGS = sorted(p for p in ALL if p.parent.name == "zoo" and re.search(r"-leg\d+$", p.stem))
# a model's last leg: its highest -legN, unless recipes/zoo/<model>.yaml is (e.g. a fine-tuning after a leg-1 training)
LAST_LEGS = [
    p
    for p in LEGS
    if p == max(q for q in LEGS if zoo_model(q) == zoo_model(p)) and not p.with_name(f"{zoo_model(p)}.yaml").is_file()
]


@pytest.mark.parametrize("path", LAST_LEGS, ids=rel)
def test_the_last_leg_is_the_recipe_the_bundle_recorded(path: Path) -> None:
    """A model's last training leg is the recipe its published bundle recorded (out_dir, init_from and the logger
    aside: they named the training machine's folders), so the card's rebuild commands reproduce it."""
    recorded = json.loads((ROOT / "zoo" / "models" / zoo_model(path) / "config.json").read_text())["recipe"]
    ours = json.loads(json.dumps(to_container(load_train_config(path))))
    for section, defaults in (("model", ModelConfig()), ("optim", OptimConfig())):
        # a setting added after the bundle was recorded must hold its default (what the bundle's training did)
        newer = {k: v for k, v in to_container(defaults).items() if k not in recorded[section]}
        assert ours[section] == {**recorded[section], **newer}, section
    for key in ("sources", "batch_size", "context_length", "scenario"):
        assert ours["data"][key] == recorded["data"][key], key
    assert Path(ours["data"]["paths"][0]).name == Path(recorded["data"]["paths"][0]).name
    for key in ("max_steps", "precision", "seed"):
        assert ours["trainer"][key] == recorded["trainer"][key], key


@pytest.mark.parametrize("path", GENERIC, ids=rel)
def test_generic_recipe_follows_the_dataset_horizon(path: Path, tmp_path: Path) -> None:
    """No dataset, scenario or horizon in the file: model.max_steps follows the manifest of the dataset given on
    the command line (context_length None = the whole horizon, resolved by the data module), unless set."""
    cfg = load(path)
    assert cfg.data.paths == [] and cfg.data.context_length is None and cfg.data.scenario is None
    if isinstance(cfg, FinetuneConfig):
        return
    data = tmp_path / "di2d-v1"
    data.mkdir()
    (data / "manifest.json").write_text(json.dumps({"scenario": {"name": "di2d", "n_steps": 40}}))
    assert load_train_config(path, [f"data.paths=[{data}]"]).model.max_steps == 40
    assert load_train_config(path, [f"data.paths=[{data}]", "model.max_steps=64"]).model.max_steps == 64


@pytest.mark.parametrize("command", ["train", "finetune"])
def test_a_required_dataset_left_out_is_one_line(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    """The generic recipes leave data.paths to the command line: without it, one line names the key and what to
    pass, before any model or Lightning is loaded."""
    from ttompc.cli import main

    model = ["--model", "no-such-model"] if command == "finetune" else []
    assert (
        main([command, str(RECIPES / "generic" / f"{'pretrain' if command == 'train' else command}.yaml"), *model]) == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "data.paths" in err and "pass data.paths=[" in err and "generate" in err, err


@pytest.mark.parametrize("path", [p for p in ALL if is_finetune(p)], ids=rel)
def test_finetuning_recipe_mixes_the_source_models_dataset(path: Path) -> None:
    """DAgger mixes new rollouts with the open-loop data the source model was trained on (same normalisation)."""
    cfg = load_finetune_config(path)
    assert 0.0 < cfg.data.open_loop_fraction < 1.0
    if path.parent.name == "generic":
        return
    source = source_recipe(path)
    assert source.is_file(), f"{path.name} fine-tunes a model from {source.name}, which is missing"
    assert cfg.data.paths == load_train_config(source).data.paths


def test_every_named_recipe_exists() -> None:
    """Cards, README, docs, scripts and code name recipes by path: each of those paths is a file."""
    texts = [
        ROOT / "README.md",
        ROOT / "Makefile",
        *(ROOT / "docs").glob("*.md"),
        *(ROOT / "zoo").glob("*.md"),
        *(ROOT / "scripts").glob("*"),
        *(ROOT / "ttompc").rglob("*.py"),
        *ALL,
    ]
    named = {m for t in texts for m in re.findall(r"(?<![\w:/])recipes/[\w.-]+/[\w.-]+\.yaml", t.read_text())}
    assert named, "the pattern finds recipe paths"
    assert sorted(n for n in named if not (ROOT / n).is_file()) == []
    cards = [p for p in (ROOT / "zoo").glob("*.md") if p.stem != "README"]
    for card in cards:
        recipe = re.search(r"^recipe: (\S+)$", card.read_text(), re.MULTILINE)
        assert recipe and (ROOT / recipe.group(1)).is_file(), card.name


def test_unknown_key_and_wrong_type_name_the_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"optim\.learning_rate"):
        load_train_config(RECIPES / "freeflyer" / "tiny.yaml", ["optim.learning_rate=1e-3"])
    with pytest.raises(ConfigError, match=r"trainer\.max_steps"):
        load_train_config(RECIPES / "freeflyer" / "tiny.yaml", ["trainer.max_steps=many"])
    with pytest.raises(ConfigError, match=r"dagger\.iteration"):
        load_finetune_config(RECIPES / "freeflyer" / "finetune.yaml", ["dagger.iteration=3"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("model:\n  n_embd: 64\n  n_heads: 4\n")
    with pytest.raises(ConfigError, match="n_heads"):
        load_train_config(bad)
    with pytest.raises(ConfigError, match="divisible"):
        load_train_config(RECIPES / "freeflyer" / "tiny.yaml", ["model.n_head=5"])


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_gpu_pretrain_script_builds_a_loadable_config(scenario: str, tmp_path: Path) -> None:
    """scripts/gpu_pretrain.sh cannot run here (no GPU); its training overrides must still load."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "DRY_RUN": "1", "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    out = subprocess.run(
        ["bash", "scripts/gpu_pretrain.sh", scenario, str(tmp_path)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert f"config OK (recipes/{scenario}/paper-pretrain.yaml" in out.stdout


def test_gpu_pretrain_script_rejects_an_unknown_scenario(tmp_path: Path) -> None:
    import subprocess

    out = subprocess.run(
        ["bash", "scripts/gpu_pretrain.sh", "nope", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 2 and out.stderr.count("\n") == 1
    assert "no recipe recipes/nope/paper-pretrain.yaml" in out.stderr
