"""Generation: seeds, failures, splits, rtg/ctg, resume, ranks, manifest, card, CLI (fake scenario and solver)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import data_fakes as fakes
import helpers
import numpy as np
import pytest

from ttompc.cli import main as cli_main
from ttompc.data.cards import parse_front_matter
from ttompc.data.config import GenerateConfig, SplitConfig
from ttompc.data.distributed import RankInfo, rank_info
from ttompc.data.generate import GenerationError, finalize, generate, split_of
from ttompc.data.schema import problem_from_row
from ttompc.data.shards import read_shard
from ttompc.scenarios import get_scenario
from ttompc.seeding import problem_seed

PROBLEMS, SHARD = 60, 16


def _cfg(out: Path, **kw) -> GenerateConfig:
    base = dict(
        scenario="data-fake",
        problems=PROBLEMS,
        out=str(out),
        shard_size=SHARD,
        workers=1,
        seed=7,
        solver=fakes.SOLVER,
        card_dir=None,
        splits=SplitConfig(0.6, 0.2, 0.2),
    )
    return GenerateConfig(**{**base, **kw})


def _parquet_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.glob("*/*.parquet"))}


def _rows(root: Path, split: str | None = None) -> list[dict]:
    files = sorted(root.glob(f"{split or '*'}/*.parquet"))
    return [r for f in files for r in read_shard(f).with_format("numpy")]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("gen") / "fake-v1"
    manifest = generate(_cfg(out), progress=False)
    assert manifest is not None
    return out, manifest


def test_problem_seeds_are_distinct_and_independent_of_workers() -> None:
    seeds = [problem_seed(0, i) for i in range(5000)]
    assert len(set(seeds)) == len(seeds)
    assert problem_seed(0, 123) == problem_seed(0, 123) != problem_seed(1, 123)
    assert int(np.random.SeedSequence(0).spawn(4)[3].generate_state(1, np.uint64)[0] >> np.uint64(1)) == seeds[3]


def test_rows_failures_and_counts(dataset: tuple[Path, dict]) -> None:
    out, manifest = dataset
    sc = get_scenario("data-fake")
    rows = _rows(out)
    failures = {f["problem_id"]: f for f in manifest["failures"]}
    for pid in range(PROBLEMS):  # the fake's failure rules, recomputed from the seed
        p = sc.sample(np.random.default_rng(problem_seed(7, pid)))
        stage = "validate" if p.x0[2] > 0.97 else "rel" if p.x0[0] > 0.93 else "scp" if p.goal[1] < 0.08 else None
        got = sorted(r["source"] for r in rows if r["problem_id"] == pid)
        expected = {"validate": [], "rel": [], "scp": ["rel"], None: ["rel", "scp"]}[stage]
        assert got == expected, pid
        assert (failures[pid]["stage"] if pid in failures else None) == stage
    assert failures, "the fixture should contain failures"
    counts = manifest["counts"]
    assert counts["rows"]["total"] == len(rows) == sum(manifest["splits"]["rows"].values())
    assert sum(counts["failures"].values()) == len(failures)
    assert all(r["seed"] == problem_seed(7, int(r["problem_id"])) for r in rows)


def test_rtg_ctg_and_representations_match_recomputation(dataset: tuple[Path, dict]) -> None:
    out, _ = dataset
    sc = get_scenario("data-fake")
    rows = _rows(out)
    assert any(r["ctg"][0] > 0 for r in rows), "some trajectories should cross the keep-out zone"
    for r in rows:
        problem = problem_from_row(sc, r)
        helpers.assert_rtg_ctg_by_hand(sc, problem, r, rtol=1e-5)
        np.testing.assert_allclose(r["states"], sc.to_model_states(problem, r["states_opt"]), rtol=1e-6)
        np.testing.assert_allclose(r["goal"], sc.model_goal(problem), rtol=1e-6)
        np.testing.assert_array_equal(r["target_actions"], r["actions"])
        np.testing.assert_array_equal(r["target_next_states"], r["states"][1:])
        np.testing.assert_allclose(sc.rollout(problem, r["actions"].astype(float)), r["states_opt"], atol=1e-5)
        assert r["iteration"] == -1 and r["cost"] == pytest.approx(sc.cost(r["actions"]), rel=1e-5)


def test_splits_by_problem_are_disjoint_and_follow_fractions(dataset: tuple[Path, dict]) -> None:
    out, manifest = dataset
    ids = {s: {int(r["problem_id"]) for r in _rows(out, s)} for s in ("train", "val", "test")}
    assert not (ids["train"] & ids["val"]) and not (ids["train"] & ids["test"]) and not (ids["val"] & ids["test"])
    assert {s: len(v) for s, v in ids.items()} == manifest["splits"]["problems"]
    splits = SplitConfig(0.9, 0.05, 0.05)
    names = [split_of(i, splits) for i in range(20_000)]
    for name, frac in splits.fractions().items():
        share = names.count(name) / len(names)
        assert abs(share - frac) < 4 * np.sqrt(frac * (1 - frac) / len(names))
    assert [split_of(i, dataclasses.replace(splits, salt=1)) for i in range(50)] != names[:50]


def test_norm_stats_are_the_train_split_moments(dataset: tuple[Path, dict]) -> None:
    out, manifest = dataset
    train = _rows(out, "train")
    states = np.concatenate([r["states"][:-1] for r in train]).astype(np.float64)
    rtg = np.concatenate([r["rtg"] for r in train]).astype(np.float64)
    stats = manifest["norm_stats"]
    np.testing.assert_allclose(stats["mean"]["states"], states.mean(0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(stats["std"]["states"], states.std(0), rtol=1e-9)
    np.testing.assert_allclose(stats["mean"]["rtg"], [rtg.mean()], rtol=1e-9)


def test_resume_after_interruption_is_byte_identical(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    ref, _ = dataset
    out = tmp_path / "fake-v1"
    written = []
    assert generate(_cfg(out, max_shards=2), progress=False, on_shard=written.append) is None
    assert [m["index"] for m in written] == [0, 1] and not (out / "manifest.json").exists()
    generate(_cfg(out, workers=2), progress=False, on_shard=written.append)
    assert [m["index"] for m in written] == [0, 1, 2, 3]  # done shards were skipped, none repeated
    assert _parquet_bytes(out) == _parquet_bytes(ref)
    # a lost and a truncated shard are regenerated, identically
    (out / "train" / "shard-00001.parquet").unlink()
    victim = out / "train" / "shard-00002.parquet"
    victim.write_bytes(victim.read_bytes()[:100])
    generate(_cfg(out), progress=False, on_shard=written.append)
    assert [m["index"] for m in written[4:]] == [1, 2]
    assert _parquet_bytes(out) == _parquet_bytes(ref)
    manifest = json.loads((out / "manifest.json").read_text())
    ref_manifest = json.loads((ref / "manifest.json").read_text())
    assert manifest["shards"] == ref_manifest["shards"] and manifest["norm_stats"] == ref_manifest["norm_stats"]


def test_two_ranks_generate_disjoint_complete_shards(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    ref, _ = dataset
    out = tmp_path / "fake-v1"
    by_rank: dict[int, list[int]] = {0: [], 1: []}
    for rank in (1, 0):  # rank 0 last: it writes the manifest once all shards exist
        result = generate(
            _cfg(out), RankInfo(rank, 2), progress=False, on_shard=lambda m, r=rank: by_rank[r].append(m["index"])
        )
        assert (result is None) == (rank == 1)
    assert by_rank == {0: [0, 2], 1: [1, 3]}
    assert _parquet_bytes(out) == _parquet_bytes(ref)


def test_rank_info_from_torchrun_and_slurm() -> None:
    assert rank_info({}) == RankInfo(0, 1, 0)
    assert rank_info({"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1"}) == RankInfo(3, 4, 1)
    assert rank_info({"SLURM_PROCID": "2", "SLURM_NTASKS": "3"}) == RankInfo(2, 3, 0)
    with pytest.raises(ValueError, match="RANK=4"):
        rank_info({"RANK": "4", "WORLD_SIZE": "4"})


def test_mismatched_generation_is_refused(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    out = tmp_path / "x"
    generate(_cfg(out, problems=20), progress=False)
    with pytest.raises(GenerationError, match="seed"):
        generate(_cfg(out, problems=20, seed=8), progress=False)
    with pytest.raises(GenerationError, match="beyond"):
        generate(_cfg(out, problems=10), progress=False)


def test_a_folder_from_before_the_solver_path_record_continues_on_the_path_it_was_made_with(tmp_path: Path) -> None:
    """Fingerprints record the resolved solver path; one without (written while ``auto`` had no kernel) ran what
    ``piqp`` runs now: the default (now the Riccati kernel first) is refused, ``backend=piqp`` continues it, and the
    manifest and card name the chain."""
    out = tmp_path / "old"
    generate(_cfg(out, problems=20), progress=False)
    path = out / "meta" / "generation.json"
    stored = json.loads(path.read_text())
    assert stored["solver_path"] == {"chain": ["riccati", "piqp", "qoco", "clarabel"], "trust_norm": "linf"}
    del stored["solver_path"]
    path.write_text(json.dumps(stored))
    with pytest.raises(GenerationError, match=r"solver_path.*backend=piqp"):
        finalize(_cfg(out, problems=20))
    manifest = finalize(_cfg(out, problems=20, backend="piqp"))
    assert manifest["solver_path"]["chain"] == ["piqp", "qoco", "clarabel"]
    assert "(backend: piqp: solvers piqp → qoco → clarabel, linf trust region)" in (out / "README.md").read_text()


def test_card_header_is_valid_and_folder_loads_by_name(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    import datasets

    out, manifest = dataset
    text = (out / "README.md").read_text()
    meta = parse_front_matter(text)
    assert {"license", "task_categories", "tags", "size_categories", "configs", "dataset_info"} <= set(meta)
    assert meta["size_categories"] == ["n<1K"]
    files = meta["configs"][0]["data_files"]
    hf = {"train": "train", "validation": "val", "test": "test"}
    for entry in files:
        assert sorted(out.glob(entry["path"])), entry
    names = [f["name"] for f in meta["dataset_info"]["features"]]
    assert names == list(manifest["features"])
    for section in (
        "## Summary",
        "## Structure",
        "## Generation procedure",
        "## Splits",
        "## Normalisation",
        "## Known limitations",
        # the scenario as a later process loads it again: its spec (a test scenario is module:Class, not a name)
        f"ttompc generate --scenario {manifest['scenario'].get('spec', 'data-fake')} --problems 60 --seed 7 "
        "--shard-size 16 --splits 0.6,0.2,0.2",
        "x [m]",
        "Δvx [m/s]",
    ):
        assert section in text
    loaded = datasets.load_dataset(str(out), streaming=True)
    for entry in files:
        split = entry["split"]
        assert sum(1 for _ in loaded[split]) == manifest["splits"]["rows"][hf[split]]


def test_cli_generate_writes_dataset_and_card_copy(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cards = tmp_path / "cards"
    cards.mkdir()
    out = tmp_path / "cli-set"
    argv = [
        "generate",
        "--scenario",
        "data-fake",
        "--problems",
        "12",
        "--out",
        str(out),
        "--shard-size",
        "5",
        "--workers",
        "1",
        "--seed",
        "3",
        "--solver",
        fakes.SOLVER,
        "--splits",
        "0.5,0.25,0.25",
        "--no-progress",
        f"card_dir={cards}",
    ]
    assert cli_main(argv) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    manifest = json.loads((out / "manifest.json").read_text())
    assert summary["rows"] == manifest["counts"]["rows"]
    assert manifest["generation"]["splits"] == {"train": 0.5, "val": 0.25, "test": 0.25, "salt": 0}
    assert (cards / "cli-set.md").read_text() == (out / "README.md").read_text()
    assert cli_main([*argv, "--finalize"]) == 0


def test_card_is_written_only_inside_out_unless_asked(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # a `data_cards/` folder in the current directory must not receive a copy named after the folder
    (tmp_path / "data_cards").mkdir()
    monkeypatch.chdir(tmp_path)
    default = GenerateConfig().card_dir
    for parent in ("a", "b"):
        out = tmp_path / parent / "set"
        assert generate(_cfg(out, problems=20, card_dir=default), progress=False) is not None
        assert parse_front_matter((out / "README.md").read_text())["configs"]
    assert list((tmp_path / "data_cards").iterdir()) == []
    asked = tmp_path / "cards" / "nested"  # an explicit copy goes exactly there (folder created)
    generate(_cfg(tmp_path / "a" / "set", problems=20, card_dir=str(asked)), progress=False)
    assert (asked / "set.md").read_text() == (tmp_path / "a" / "set" / "README.md").read_text()


def test_files_get_normal_modes(dataset: tuple[Path, dict], tmp_path: Path) -> None:
    import os

    old = os.umask(0o022)
    try:
        out = tmp_path / "modes"
        generate(_cfg(out, problems=20), progress=False)
    finally:
        os.umask(old)
    files = [p for p in out.rglob("*") if p.is_file()]
    assert {"manifest.json", "README.md", "generation.json"} <= {p.name for p in files}
    assert any(p.suffix == ".parquet" for p in files)
    assert {p.name: oct(p.stat().st_mode & 0o777) for p in files} == {p.name: "0o644" for p in files}


def test_split_left_empty_is_refused_before_any_work(tmp_path: Path) -> None:
    out = tmp_path / "small"
    # 20 problems at 5% test: the id hash gives the test split no problem at salt 0
    with pytest.raises(GenerationError, match=r"split\(s\) test would get no problem.*splits\.test=0"):
        generate(_cfg(out, problems=20, splits=SplitConfig(0.9, 0.05, 0.05)), progress=False)
    assert not out.exists()
    manifest = generate(_cfg(out, problems=20, splits=SplitConfig(0.9, 0.1, 0.0)), progress=False)
    assert manifest is not None and manifest["splits"]["problems"]["val"] == 1


def test_cli_refuses_empty_split_in_one_line(tmp_path: Path) -> None:
    import subprocess
    import sys

    out = tmp_path / "twenty"
    res = subprocess.run(
        [sys.executable, "-m", "ttompc.cli", "generate", "scenario=freeflyer", "problems=20", f"out={out}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr and "split(s) test would get no problem" in res.stderr
    assert "splits.test=0" in res.stderr and not out.exists()


def test_regenerated_shard_has_the_rows_of_an_uninterrupted_run(tmp_path: Path) -> None:
    """The real solvers: a shard regenerated by a fresh process (which solves its problems first, not after the
    earlier shards' as the uninterrupted run did) holds the same rows bit for bit, wall-clock timings aside."""
    from ttompc.solvers.backends import clear_solver_cache

    timings = {"solve_time", "solver_time"}
    cfg = _cfg(tmp_path / "ff", scenario="freeflyer", problems=4, shard_size=2, seed=0, solver=GenerateConfig.solver)
    cfg.splits = SplitConfig(1.0, 0.0, 0.0)
    clear_solver_cache()  # as in a new process
    generate(cfg, progress=False)
    reference = _rows(Path(cfg.out))
    (Path(cfg.out) / "meta" / "shard-00001.json").unlink()
    clear_solver_cache()  # the resumed run is a new process
    written: list[dict] = []
    generate(cfg, progress=False, on_shard=written.append)
    assert [m["index"] for m in written] == [1]
    rows = _rows(Path(cfg.out))
    assert [r["problem_id"] for r in rows] == [r["problem_id"] for r in reference] and len(rows) >= 6
    for row, ref in zip(rows, reference, strict=True):
        assert row.keys() == ref.keys()
        for key in row.keys() - timings:
            np.testing.assert_array_equal(row[key], ref[key], err_msg=f"problem {row['problem_id']} {key}")


def test_scp_rows_carry_costates_and_shards_without_them_still_load(tmp_path: Path) -> None:
    """With the default solver path SCP rows store the optimum's costates (∂J*/∂s_k, k ≥ 1; the fixed start NaN),
    REL rows none; a shard written before the column reads back with no gradient target."""
    import pyarrow.parquet as pq
    import torch

    from ttompc.data.config import DataConfig
    from ttompc.data.datamodule import TrajectoryDataModule

    out = tmp_path / "q"
    helpers.tiny_dataset(out, "quadrotor", 2, (1.0, 0.0, 0.0), shard_size=2, seed=5)
    (path,) = sorted((out / "train").glob("*.parquet"))
    rows = read_shard(path)
    lam = {s: np.asarray(c) for s, c in zip(rows["source"], rows["costates"], strict=True)}
    assert np.isfinite(lam["scp"][1:]).all() and np.isnan(lam["scp"][0]).all() and np.isnan(lam["rel"]).all()
    table = pq.read_table(path)
    pq.write_table(table.drop_columns(["costates"]), path)  # as written before the column
    dm = TrajectoryDataModule(DataConfig(paths=[str(out)], batch_size=2, verify_checksums=False))
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert not batch["grad_mask"].any() and bool(torch.isfinite(batch["value_grad"]).all())
