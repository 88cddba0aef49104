"""Hugging Face-style dataset cards written from a dataset manifest.

The YAML header's ``configs:`` section maps each split to its shard glob, so ``datasets.load_dataset(<folder>)``
loads the folder by name; ``dataset_info`` carries the exact features. The body documents fields with units,
generation, splits, normalisation and known limitations. The hub's validator needs the network, so tests parse
and check the header themselves (``parse_front_matter``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from datasets import DatasetInfo, Features

from ttompc.data.shards import atomic_write_text

HF_SPLIT = {"train": "train", "val": "validation", "test": "test"}  # folder -> hub split name
LICENSE = "mit"


def size_category(n: int) -> str:
    for bound, label in ((1_000, "n<1K"), (10_000, "1K<n<10K"), (100_000, "10K<n<100K"), (1_000_000, "100K<n<1M")):
        if n < bound:
            return label
    return "1M<n<10M"


def front_matter(manifest: dict[str, Any]) -> dict[str, Any]:
    rows = manifest["splits"]["rows"]
    splits = [s for s in HF_SPLIT if rows[s] > 0]
    features = DatasetInfo(features=Features.from_dict(manifest["features"]))._to_yaml_dict()["features"]
    return {
        "license": LICENSE,
        "pretty_name": f"ttompc {manifest['scenario']['name']} trajectories ({manifest['name']})",
        "task_categories": ["robotics", "reinforcement-learning"],
        "tags": [
            "trajectory-optimization",
            "model-predictive-control",
            "decision-transformer",
            "sequential-convex-programming",
            "ttompc",
            manifest["scenario"]["name"],
        ],
        "size_categories": [size_category(manifest["counts"]["rows"]["total"])],
        "configs": [
            {
                "config_name": "default",
                "data_files": [{"split": HF_SPLIT[s], "path": f"{s}/*.parquet"} for s in splits],
            }
        ],
        "dataset_info": {
            "features": features,
            "splits": [{"name": HF_SPLIT[s], "num_examples": rows[s]} for s in splits],
        },
    }


def _fields_table(manifest: dict[str, Any]) -> str:
    sc = manifest["scenario"]
    N, n, m = sc["n_steps"], sc["state_dim"], sc["control_dim"]
    states, controls = ", ".join(sc["state_labels"]), ", ".join(sc["control_labels"])
    cost = {"l1": "‖u‖₁", "l2": "‖u‖₂", "quad": "½‖u‖₂²"}[sc["cost_norm"]]
    lines = [
        "| field | shape | meaning (units) |",
        "|---|---|---|",
        "| `problem_id`, `seed` | () | problem index and its seed (`SeedSequence(root, spawn_key=(id,))`) |",
        "| `source` | () | `rel` (relaxed problem), `scp` (full problem), `dagger` (closed-loop rows) |",
        "| `iteration` | () | DAgger iteration, −1 for open-loop rows |",
        f"| `states` | ({N + 1}, {n}) | x₀..x_N in the model representation: {states} |",
        f"| `actions` | ({N}, {m}) | u₀..u_(N−1): {controls} |",
        f"| `goal` | ({n},) | target state, model representation (same units as `states`) |",
        f"| `rtg` | ({N},) | reward-to-go −Σ_(τ≥t) c(u_τ), c(u) = {cost} (action units) |",
        f"| `ctg` | ({N},) | constraint-to-go Σ_(τ≥t) violated keep-out constraints at x_τ, τ < {N} (count) |",
        f"| `target_actions`, `target_next_states` | ({N}, {m}), ({N}, {n}) | training targets (open loop: "
        "`actions`, `states[1:]`; DAgger: expert labels) |",
        f"| `states_opt`, `x0`, `goal_opt`, `dt`, `feat_*` | ({N + 1}, {n}), ({n},), ({n},), () | problem in the "
        "optimisation representation (dt in s), enough to rebuild and re-solve it |",
        "| `cost`, `iterations`, `status`, `solve_time`, `solver_time`, `violation` | () | solver statistics "
        "(cost = Σc(u), times in s, violation = max nonlinear constraint violation) |",
    ]
    return "\n".join(lines)


def render_card(manifest: dict[str, Any]) -> str:
    sc, counts, splits = manifest["scenario"], manifest["counts"], manifest["splits"]
    gen, solver = manifest["generation"], manifest["solver"]
    header = yaml.safe_dump(front_matter(manifest), sort_keys=False, allow_unicode=True)
    fails = ", ".join(f"{k}: {v}" for k, v in counts["failures"].items())

    fr = gen["splits"]
    reproduce = (
        f"ttompc generate --scenario {sc.get('spec', sc['name'])} --problems {gen['problems']} "
        f"--seed {manifest['root_seed']} "
        f"--shard-size {gen['shard_size']} --splits {fr['train']},{fr['val']},{fr['test']} --split-salt {fr['salt']} "
        f"--out data/{manifest['name']}" + (f" --backend {gen['backend']}" if gen["backend"] else "")
    )

    def fmt(x: float | None, spec: str) -> str:
        return "n/a" if x is None else format(x, spec)

    path = manifest["solver_path"]
    solvers = f"solvers {' → '.join(path['chain'])}, {path['trust_norm']} trust region"
    solver_lines = "\n".join(
        f"- {s.upper()}: {v['rows']} rows, mean solve time {fmt(v['mean_solve_time'], '.3f')} s, "
        f"mean iterations {fmt(v['mean_iterations'], '.2f')}, mean cost {fmt(v['mean_cost'], '.4g')}"
        for s, v in solver.items()
    )
    return f"""---
{header}---

# {manifest["name"]}: {sc["name"]} trajectory dataset

## Summary
Optimal trajectories of the `{sc["name"]}` scenario (version {sc["version"]}) for training trajectory transformers
(Transformer-based MPC, RA-L 2024). Each of {counts["problems"]} random problems is solved twice: the relaxed
problem without keep-out constraints (REL) and the full non-convex problem by sequential convex programming (SCP)
warm-started from REL. Both solutions are stored as rows sharing `problem_id`: {counts["rows"]["total"]} rows
({counts["rows"]["rel"]} REL, {counts["rows"]["scp"]} SCP). Generated by `ttompc generate` (code
`{manifest["code_version"]}`, root seed {manifest["root_seed"]}).

Load it with `datasets.load_dataset("<this folder>")` or stream it with `ttompc.data.TrajectoryDataModule`.

## Structure
Parquet shards `<split>/shard-<k>.parquet`; shard k holds problems [k·{gen["shard_size"]},
(k+1)·{gen["shard_size"]}). `manifest.json` lists every file with its row count and sha256. One row per trajectory,
N = {sc["n_steps"]} steps, all arrays with fixed shapes (float32 unless stated; `x0`, `goal_opt`, `dt` float64):

{_fields_table(manifest)}

## Generation procedure
Problem i is sampled with `numpy.random.default_rng(seed_i)`, seed_i from `SeedSequence({manifest["root_seed"]},
spawn_key=(i,))`, so the dataset does not depend on the number of workers or ranks. Solver: `{gen["solver"]}`
(backend: {gen["backend"] or "default"}: {solvers}). Reproduce (any number of workers or ranks, resumable):
`{reproduce}`. A REL or SCP solve that is not optimal/feasible is not stored; it is
recorded in the manifest's `failures` list (problem_id, seed, stage, status). Failures by stage: {fails}.

{solver_lines}

## Splits
By problem, never by row: REL and SCP rows of a problem are always in the same split ({splits["method"]};
fractions {splits["fractions"]}, salt {splits["salt"]}). Problems per split: {splits["problems"]}; rows per split:
{splits["rows"]}.

## Normalisation
`manifest.json` → `norm_stats` holds the global per-dimension mean and std (over rows and time steps) of states
(x₀..x_(N−1)), actions, goals, rtg and ctg, computed on the **train** split only. Models normalise as
(x − μ)/(σ + 1e-6) with these statistics, including for DAgger data added later.

## Known limitations
- Problems with a failed SCP keep their REL row (a valid relaxed solution) but have no SCP row.
- ctg counts violations of the inflated keep-out zones at the discrete states only, not between them.
- Solve times depend on the machine and backend; they are stored for analysis, not as benchmarks.
- The goal is constant over each trajectory (no time-varying targets), as in the reference datasets.
"""


def write_card(root: str | Path, manifest: dict[str, Any], copy_dir: str | Path | None = None) -> Path:
    """Write ``<root>/README.md`` and, only when ``copy_dir`` is given, a copy ``<copy_dir>/<name>.md`` (the folder
    is created). Nothing is written outside ``root`` unless asked: two datasets with the same folder name must not
    overwrite each other's card in whatever directory the command ran from."""
    path = Path(root) / "README.md"
    text = render_card(manifest)
    atomic_write_text(path, text)
    if copy_dir is not None:
        atomic_write_text(Path(copy_dir) / f"{manifest['name']}.md", text)
    return path


def parse_front_matter(text: str) -> dict[str, Any]:
    """The YAML header of a card (between the leading ``---`` lines)."""
    if not text.startswith("---\n"):
        raise ValueError("card does not start with a YAML front matter block")
    end = text.index("\n---\n", 4)
    return yaml.safe_load(text[4:end])
