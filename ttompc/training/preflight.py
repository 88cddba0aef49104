"""Checks of a training run against its machine, its data and its output folder, made before Lightning is imported
or anything is written (``prepare_run``, which ``ttompc.training.run.train`` runs itself, so that the Python entry
refuses what ``ttompc train`` refuses, in the same words): the devices exist here, the datasets are finished ones of
one scenario, the model fits the data's horizon (``check_model_fits``), and ``trainer.out_dir`` is this run's
(``claim_run``).

A run claims its ``out_dir`` with ``run.json``: the identity of what its checkpoints are — the scenario, a
fingerprint of the data (the manifests' shard checksums), the architecture (the model fields that shape the weights)
and the weights it started from (``init_from``, ``optim.trainable``). A later ``train`` resumes those checkpoints only
with the same identity; another scenario, data set or architecture in the same folder is refused in one line (it
would otherwise resume, say, free-flyer weights on quadrotor data, or fail to load them). Folders from before
``run.json`` are judged by their newest checkpoint's hyper-parameters (scenario and architecture).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from ttompc.data.manifests import check_datasets
from ttompc.data.shards import atomic_write_json
from ttompc.errors import ConfigError
from ttompc.outputs import claim_folder
from ttompc.ranges import check_devices
from ttompc.training.config import TrainConfig

RUN_FILE = "run.json"
# the model fields that shape the weights: a resumed run must keep them
ARCHITECTURE = (
    "layout",
    "n_embd",
    "n_layer",
    "n_head",
    "mlp_ratio",
    "max_steps",
    "bias",
    "activation",
    "value_width",
    "value_form",
    "value_rank",
    "value_activation",
    "state_dim",
    "control_dim",
)


def prepare_run(cfg: TrainConfig) -> list[dict[str, Any]]:
    """Every check of a run that reads its data from ``cfg.data`` (module doc), in the order the CLI reports them;
    claims ``trainer.out_dir`` (writes its ``run.json``) and returns the datasets' manifests. Raises ``ConfigError``
    or ``UserError`` in one line."""
    check_devices(cfg)
    manifests = check_datasets(cfg.data)
    check_model_fits(cfg, manifests)
    claim_run(cfg, manifests)
    return manifests


def check_model_fits(cfg: TrainConfig, manifests: list[dict[str, Any]]) -> None:
    """``model.max_steps`` (the timestep-embedding table) must hold the data's whole horizon N."""
    if not manifests:
        return
    scenario = manifests[0]["scenario"]
    n_steps = int(scenario["n_steps"])
    if cfg.model.max_steps < n_steps:
        raise ConfigError(
            f"invalid model.max_steps={cfg.model.max_steps}: the {scenario['name']} data of {cfg.data.paths[0]} has "
            f"{n_steps}-step trajectories",
            f"set model.max_steps >= {n_steps} (or leave it out: it follows the data)",
        )


def run_identity(
    cfg: TrainConfig, manifests: list[dict[str, Any]], scenario: dict[str, Any] | None = None
) -> dict[str, Any]:
    """What this run's checkpoints would be: scenario, data fingerprint, architecture, starting weights. Data that
    does not come from datasets (a DataModule given to ``train``: no ``manifests``, its ``scenario`` name and token
    dimensions given) has no fingerprint: the identity leaves ``data`` out, and it is not compared."""
    scenario = scenario if scenario is not None else manifests[0]["scenario"] if manifests else {}
    model = {
        **{k: getattr(cfg.model, k) for k in ARCHITECTURE},
        "state_dim": scenario.get("state_dim", cfg.model.state_dim),
        "control_dim": scenario.get("control_dim", cfg.model.control_dim),
    }
    shards = json.dumps([m.get("shards") for m in manifests], sort_keys=True)
    data = {"data": hashlib.sha256(shards.encode()).hexdigest()[:16]} if manifests else {}
    return {
        "scenario": scenario.get("name"),
        **data,
        "architecture": model,
        "init_from": cfg.init_from,
        "trainable": cfg.optim.trainable,
    }


def claim_run(cfg: TrainConfig, manifests: list[dict[str, Any]], scenario: dict[str, Any] | None = None) -> None:
    """Make ``trainer.out_dir`` this run's: a new or empty folder, or one of ``train``'s whose checkpoints were made
    by the same run identity (``run_identity``, of ``manifests`` or of ``scenario``; with ``trainer.resume=false``
    any of ``train``'s folders, whose checkpoints are then replaced). Writes ``run.json`` (keeping the stored data
    fingerprint when this run has none); raises ``ConfigError``/``UserError`` naming what differs."""
    out = Path(cfg.trainer.out_dir)
    claim_folder(out, "train", lambda f: (f / RUN_FILE).is_file() or (f / "checkpoints").is_dir())
    mine = run_identity(cfg, manifests, scenario)
    stored = _stored_identity(out) if cfg.trainer.resume else None
    differ = [_difference(k, stored[k], mine[k]) for k in mine if stored and k in stored] if stored else []
    shown = "; ".join(d for d in differ if d)
    if shown:
        raise ConfigError(
            f"trainer.out_dir={out} holds checkpoints of another run ({shown}): resuming them would train the "
            "wrong model",
            "choose a new trainer.out_dir, or pass trainer.resume=false to start over there",
        )
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / RUN_FILE, {**(stored or {}), **mine})


def _stored_identity(out: Path) -> dict[str, Any] | None:
    """The identity of the checkpoints in ``out``: its ``run.json``, else (older folders) the newest checkpoint's
    scenario and architecture; None when it has no checkpoint."""
    checkpoints = sorted((out / "checkpoints").glob("*.ckpt"), key=lambda p: p.stat().st_mtime, reverse=True)
    if not checkpoints:
        return None
    run_file = out / RUN_FILE
    if run_file.is_file():
        try:
            return dict(json.loads(run_file.read_text()))
        except ValueError:
            pass  # damaged: judge by the checkpoint
    import torch

    for path in checkpoints:
        try:
            hp = torch.load(path, map_location="cpu", weights_only=True)["hyper_parameters"]
        except Exception:  # a damaged checkpoint: resume_checkpoint moves it aside and says so
            continue
        arch = {k: hp["model_config"][k] for k in ARCHITECTURE if k in hp["model_config"]}
        return {"scenario": hp["scenario"], "architecture": arch}
    return None


def _difference(key: str, stored: Any, mine: Any) -> str:
    """What differs in ``key`` between the stored identity and this run's ("" when nothing does); an architecture is
    compared on the fields both record."""
    if key == "architecture":
        fields = [f"model.{k}={stored[k]} there, {mine[k]} here" for k in mine if k in stored and stored[k] != mine[k]]
        return ", ".join(fields)
    return "" if stored == mine else f"{key} {stored} there, {mine} here"
