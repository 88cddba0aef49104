"""Dataset generation: sample problems, solve REL then SCP warm-started from REL, store both solutions.

Reproducibility by construction (``docs/design.md`` lists the research code's duplicate-sample bugs this avoids):

* problem i draws from ``default_rng(problem_seed(root, i))`` with ``SeedSequence(root, spawn_key=(i,))`` — the
  same problem whatever the number of workers or ranks, never a shared RNG state;
* shard k always covers problem ids [k·K, (k+1)·K) and is written by ``ShardedFolder`` (atomic files, then
  metadata ``meta/shard-<k>.json``); an interrupted run resumes by skipping done shards;
* a problem's rows depend only on (seed, problem id): cached solvers restart for every solve, so whichever worker
  or resumed run solves it, its rows are bit-identical but for the wall-clock times (tested; 1 or 2 BLAS threads);
* splits are a hash of the problem id, so REL and SCP rows of a problem share a split.

Under torchrun/SLURM each rank generates every world_size-th shard; rank 0 (or ``ttompc generate --finalize``)
writes ``manifest.json`` and the dataset card (``README.md`` in the output folder; ``card_dir``: a copy) once every
shard exists. A split configuration that would leave a split with a positive fraction empty is refused at once.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ttompc.config import to_container
from ttompc.data.config import GenerateConfig, SplitConfig
from ttompc.data.distributed import RankInfo, rank_info
from ttompc.data.manifests import MANIFEST
from ttompc.data.resumable import META_DIR, ShardedFolder
from ttompc.data.schema import SCHEMA_VERSION, make_row, model_costates, trajectory_features
from ttompc.data.shards import SPLITS, atomic_write_json
from ttompc.errors import UserError
from ttompc.outputs import claim_folder
from ttompc.parallel import pool_map
from ttompc.policy.stats import KEYS, NormStats
from ttompc.ranges import check_devices
from ttompc.scenarios import get_scenario, scenario_spec
from ttompc.scenarios.base import InfeasibleProblemError, Scenario
from ttompc.seeding import problem_seed
from ttompc.solvers.backends import solver_path
from ttompc.version import code_version

STAGES = ("validate", "rel", "scp")


class GenerationError(UserError, RuntimeError):
    """An output folder that does not match the requested generation (other seed, scenario, shard size...), or
    settings that cannot make a dataset; ``ttompc generate`` prints it as its one error line."""


# ------------------------------------------------------------------------------------------------ determinism
def split_of(problem_id: int, splits: SplitConfig) -> str:
    """Deterministic split of a problem: u = sha256(salt:problem_id) ∈ [0, 1) against cumulative fractions."""
    digest = hashlib.sha256(f"{splits.salt}:{problem_id}".encode()).digest()
    u = int.from_bytes(digest[:8], "big") / 2.0**64
    acc = 0.0
    for name, frac in splits.fractions().items():
        acc += frac
        if u < acc:
            return name
    return "train" if splits.train > 0 else next(k for k, v in splits.fractions().items() if v > 0)


def fingerprint(cfg: GenerateConfig, scenario: Scenario) -> dict[str, Any]:
    """Everything that determines the rows of a shard (not the problem count, workers or ranks). ``backend`` is the
    name asked for, ``solver_path`` what it resolves to (chain and trust-region norm): the rows depend on the
    latter, which a name's meaning may change (``auto`` did when the Riccati kernel joined its chain)."""
    path = solver_path(cfg.backend or "auto", scenario)
    return {
        "schema_version": SCHEMA_VERSION,
        "scenario": scenario.name,
        "scenario_version": scenario.version,
        "seed": cfg.seed,
        "shard_size": cfg.shard_size,
        "splits": to_container(cfg.splits),
        "solver": cfg.solver,
        "backend": cfg.backend,
        "solver_path": {"chain": path["chain"], "trust_norm": path["trust_norm"]},
    }


def _path_before_solver_path(backend: str | None, scenario: Scenario) -> dict[str, Any]:
    """The solver path a fingerprint without one ran (fingerprints recorded none while ``auto`` was the scenario's
    ``auto_backends`` without the Riccati kernel): ``auto`` (or null) ran today's ``piqp`` chain, ``piqp`` PIQP
    alone; other names resolve as they do now."""
    name = backend or "auto"
    if name == "auto":
        chain = list(scenario.auto_backends)
    elif name == "piqp":
        chain = ["piqp"]
    else:
        chain = solver_path(name, scenario)["chain"]
    return {"chain": chain, "trust_norm": solver_path(name, scenario)["trust_norm"]}


# ------------------------------------------------------------------------------------------------ per problem
_WORKER: dict[str, Any] = {}


def _init_worker(scenario_name: str, solver: str, backend: str | None) -> None:
    """Runs once per process (after the scenario's module was imported, which registers it)."""
    module, _, func = solver.partition(":")
    _WORKER.update(
        scenario=get_scenario(scenario_name),
        solve=getattr(importlib.import_module(module), func),
        kwargs={} if backend is None else {"backend": backend},
    )


def _solve_one(task: tuple[int, int]) -> dict[str, Any]:
    """Sample and solve problem ``task = (problem_id, seed)``: its rows and, if any stage failed, a failure."""
    pid, seed = task
    scenario: Scenario = _WORKER["scenario"]
    problem = scenario.sample(np.random.default_rng(seed))
    out: dict[str, Any] = {"problem_id": pid, "rows": [], "failure": None}
    try:
        scenario.validate(problem)
    except InfeasibleProblemError as err:
        out["failure"] = {"problem_id": pid, "seed": seed, "stage": "validate", "status": str(err)}
        return out
    rel, scp = _WORKER["solve"](scenario, problem, **_WORKER["kwargs"])
    for source, res in (("rel", rel), ("scp", scp)):
        if res is None or not res.success:
            status = "skipped (REL failed)" if res is None else res.status.value
            out["failure"] = out["failure"] or {"problem_id": pid, "seed": seed, "stage": source, "status": status}
            continue
        lam = res.costates if source == "scp" else None  # the value's Sobolev targets; REL's are not J*'s
        out["rows"].append(
            make_row(
                scenario,
                problem,
                problem_id=pid,
                seed=seed,
                source=source,
                states=scenario.to_model_states(problem, res.X),
                states_opt=res.X,
                actions=res.U,
                costates=None if lam is None else model_costates(scenario, problem, lam),
                cost=res.cost,
                iterations=res.iterations,
                status=res.status.value,
                solve_time=res.solve_time,
                solver_time=res.solver_time,
                violation=res.violation,
            )
        )
    return out


# ------------------------------------------------------------------------------------------------ statistics
def _moments(rows: list[dict[str, Any]], n_steps: int) -> dict[str, dict[str, Any]]:
    """(count, mean, M2) per NormStats key over train rows; merged exactly across shards (Chan et al.)."""
    arrays = {
        "states": np.stack([r["states"][:n_steps] for r in rows]),
        "actions": np.stack([r["actions"] for r in rows]),
        "goals": np.stack([r["goal"] for r in rows]),
        "rtg": np.stack([r["rtg"] for r in rows])[..., None],
        "ctg": np.stack([r["ctg"] for r in rows])[..., None],
    }
    out = {}
    for k in KEYS:
        a = np.asarray(arrays[k], dtype=np.float32).astype(np.float64)  # the stored precision
        a = a.reshape(-1, a.shape[-1])
        mean = a.mean(axis=0)
        out[k] = {"count": len(a), "mean": mean.tolist(), "m2": ((a - mean) ** 2).sum(axis=0).tolist()}
    return out


def _merge_moments(parts: list[dict[str, dict[str, Any]]]) -> NormStats:
    mean, std = {}, {}
    for k in KEYS:
        n, mu, m2 = 0, None, None
        for p in parts:
            nb, mb, m2b = p[k]["count"], np.asarray(p[k]["mean"]), np.asarray(p[k]["m2"])
            if mu is None:
                n, mu, m2 = nb, mb, m2b
                continue
            delta, tot = mb - mu, n + nb
            mu = mu + delta * nb / tot
            m2 = m2 + m2b + delta**2 * n * nb / tot
            n = tot
        if not n or mu is None or m2 is None:
            raise GenerationError("no training rows: cannot compute normalisation statistics")
        mean[k], std[k] = mu, np.sqrt(m2 / n)
    return NormStats(mean, std)


# ------------------------------------------------------------------------------------------------ shards
def sharded_folder(cfg: GenerateConfig, scenario: Scenario) -> ShardedFolder:
    """The output folder's shards: shard k holds problems [k·shard_size, (k+1)·shard_size)."""
    return ShardedFolder(cfg.out, trajectory_features(scenario), cfg.problems, cfg.shard_size)


def _write_shard(
    folder: ShardedFolder,
    index: int,
    cfg: GenerateConfig,
    scenario: Scenario,
    outcomes: list[dict[str, Any]],
    seconds: float,
) -> dict[str, Any]:
    by_split: dict[str, list[dict[str, Any]]] = {s: [] for s in SPLITS}
    failures = []
    for o in sorted(outcomes, key=lambda o: o["problem_id"]):
        by_split[split_of(o["problem_id"], cfg.splits)].extend(o["rows"])
        if o["failure"] is not None:
            failures.append(o["failure"])
    all_rows = [r for rows in by_split.values() for r in rows]
    solver: dict[str, dict[str, float]] = {}
    for source in ("rel", "scp"):
        rs = [r for r in all_rows if r["source"] == source]
        solver[source] = {
            "rows": len(rs),
            **{f"{k}_sum": float(sum(r[k] for r in rs)) for k in ("solve_time", "solver_time", "iterations", "cost")},
        }
    return folder.write(
        index,
        by_split,
        failures=failures,
        rows={s: len(r) for s, r in by_split.items()},
        problems={s: len({r["problem_id"] for r in rows}) for s, rows in by_split.items()},
        solver=solver,
        seconds=seconds,
        train_moments=_moments(by_split["train"], scenario.n_steps) if by_split["train"] else None,
    )


def check_splits(cfg: GenerateConfig) -> dict[str, int]:
    """Problems per split (by id, before any failure); a split with a positive fraction but no problem is refused:
    a small dataset with a 5% split would silently come out without it."""
    fractions = cfg.splits.fractions()
    counts = dict.fromkeys(SPLITS, 0)
    for i in range(cfg.problems):
        counts[split_of(i, cfg.splits)] += 1
    empty = [s for s in SPLITS if fractions[s] > 0 and counts[s] == 0]
    if empty:
        raise GenerationError(
            f"split(s) {', '.join(empty)} would get no problem: {cfg.problems} problems at fractions {fractions} "
            f"assign {counts}; use more problems, larger fractions, another splits.salt, or set "
            + " and ".join(f"splits.{s}=0" for s in empty)
            + " to have none"
        )
    return counts


def generate(
    cfg: GenerateConfig,
    ranks: RankInfo | None = None,
    progress: bool = True,
    on_shard: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any] | None:
    """Generate (or resume) the dataset of ``cfg``; returns the manifest, or None if other ranks' shards are
    still missing. ``on_shard`` is called with each new shard's metadata. ``progress``: a bar on stderr (also
    subject to ``TTOMPC_PROGRESS``/``CI``, ``ttompc.progress``)."""
    from ttompc.progress import Bar

    check_devices(cfg)  # its workers within this machine's cores
    check_splits(cfg)
    ranks = ranks or rank_info()
    scenario = get_scenario(cfg.scenario)
    folder = sharded_folder(cfg, scenario)
    _check_folder(folder, cfg, scenario)
    mine = folder.mine(ranks)
    pending = folder.pending(ranks)
    if cfg.max_shards is not None:
        pending = pending[: cfg.max_shards]
    tasks = [(i, problem_seed(cfg.seed, i)) for i in folder.items(pending)]
    workers = cfg.workers or os.cpu_count() or 1
    init_args = (scenario.name, cfg.solver, cfg.backend)
    skipped = len(mine) - len(pending)
    failures = 0

    def counted(outcomes: Iterable[dict[str, Any]], bar: Bar) -> Iterator[dict[str, Any]]:
        nonlocal failures
        for outcome in outcomes:
            failures += outcome["failure"] is not None
            bar.update(1)
            bar.set_postfix(failures=failures, skipped_shards=skipped)
            yield outcome

    outcomes = pool_map(
        _solve_one, tasks, workers, _init_worker, init_args, scenarios=[scenario_spec(scenario)], pin_torch=False
    )
    with Bar(len(tasks), f"{scenario.name} rank {ranks.rank}", "problem", show=progress) as bar:
        bar.set_postfix(failures=0, skipped_shards=skipped)
        for k, batch, seconds in folder.group(pending, counted(outcomes, bar)):
            meta = _write_shard(folder, k, cfg, scenario, batch, seconds)
            if on_shard is not None:
                on_shard(meta)
    if not ranks.is_main or not folder.wait(cfg.finalize_wait_s):
        return None
    return finalize(cfg)


def _check_folder(folder: ShardedFolder, cfg: GenerateConfig, scenario: Scenario) -> None:
    """Refuse to write anywhere but a new folder or one of this generation (``claim_folder``: a folder without the
    recorded fingerprint ``meta/generation.json`` must be empty), and to mix generations: the recorded fingerprint
    must match, and no shard may lie beyond the requested problem count. Backend names match where they resolve to
    the same solver path: a folder made with ``auto`` and no recorded solver path continues with ``backend=piqp``,
    which runs what that ``auto`` ran."""
    out = folder.root
    fp = fingerprint(cfg, scenario)
    path = out / META_DIR / "generation.json"
    claim_folder(out, "generate", lambda _: path.is_file())
    if path.is_file():
        stored = json.loads(path.read_text())
        stored.setdefault("solver_path", _path_before_solver_path(stored.get("backend"), scenario))
        diff = {k: (stored.get(k), fp[k]) for k in fp if k != "backend" and stored.get(k) != fp[k]}
        if diff:
            hint = ", or a backend with the stored solver_path (older folders, which record none, used backend=piqp's)"
            raise GenerationError(
                f"{out} holds another generation (stored vs requested: {diff}); use a new folder"
                + (hint if "solver_path" in diff else "")
            )
    else:
        atomic_write_json(path, fp)
    beyond = folder.beyond()
    if beyond:
        raise GenerationError(f"{out} has shards beyond --problems {cfg.problems} ({beyond[:3]}...)")


def finalize(cfg: GenerateConfig) -> dict[str, Any]:
    """Write ``manifest.json`` and the dataset card from the shard metadata (every shard must be done)."""
    from ttompc.data.cards import write_card

    scenario = get_scenario(cfg.scenario)
    out = Path(cfg.out)
    folder = sharded_folder(cfg, scenario)
    _check_folder(folder, cfg, scenario)
    missing = folder.missing()
    if missing:
        raise GenerationError(
            f"{out}: {len(missing)} shard(s) missing or corrupt (first: {missing[:5]}); "
            "run `ttompc generate` with the same arguments to complete them"
        )
    metas = [folder.meta(k) for k in range(folder.n_shards)]
    failures = [f for m in metas for f in m["failures"]]
    rows_by_split = {s: sum(m["rows"][s] for m in metas) for s in SPLITS}
    solver = {}
    for source in ("rel", "scp"):
        n = sum(m["solver"][source]["rows"] for m in metas)
        solver[source] = {
            "rows": n,
            **{
                f"mean_{k}": (sum(m["solver"][source][f"{k}_sum"] for m in metas) / n if n else None)
                for k in ("solve_time", "solver_time", "iterations", "cost")
            },
        }
    stats = _merge_moments([m["train_moments"] for m in metas if m["train_moments"] is not None])
    manifest = {
        "schema_version": SCHEMA_VERSION,
        "name": cfg.name or out.resolve().name,
        "scenario": {
            "name": scenario.name,
            "spec": scenario_spec(scenario),  # how later commands load it (``ttompc.scenarios.find_scenario``)
            "version": scenario.version,
            "n_steps": scenario.n_steps,
            "state_dim": scenario.state_dim,
            "control_dim": scenario.control_dim,
            "cost_norm": scenario.cost_norm,
            "state_labels": list(scenario.state_labels),
            "control_labels": list(scenario.control_labels),
        },
        "generation": {k: v for k, v in to_container(cfg).items() if k not in ("out", "max_shards", "workers")},
        "root_seed": cfg.seed,
        "solver_path": solver_path(cfg.backend or "auto", scenario),  # what backend=null ran: chain, trust norm
        "code_version": code_version(),
        "counts": {
            "problems": cfg.problems,
            "rows": {"total": sum(rows_by_split.values()), **{s: solver[s]["rows"] for s in ("rel", "scp")}},
            "failures": {stage: sum(f["stage"] == stage for f in failures) for stage in STAGES},
        },
        "splits": {
            "method": "sha256(f'{salt}:{problem_id}') mapped to [0, 1) against cumulative fractions",
            "fractions": cfg.splits.fractions(),
            "salt": cfg.splits.salt,
            "problems": {s: sum(m["problems"][s] for m in metas) for s in SPLITS},
            "rows": rows_by_split,
        },
        "norm_stats": stats.to_dict(),
        "norm_stats_split": "train",
        "solver": solver,
        "features": trajectory_features(scenario).to_dict(),
        "shards": [{"index": m["index"], "start": m["start"], "stop": m["stop"], "files": m["files"]} for m in metas],
        "failures": failures,
    }
    atomic_write_json(out / MANIFEST, manifest)
    write_card(out, manifest, copy_dir=cfg.card_dir)
    return manifest
