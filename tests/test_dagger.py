"""DAgger fine-tuning (paper Alg. 1) on the short free-flyer with a tiny model: recipes, config keys, seeds, the
keep/reject rule, and two iterations interrupted twice (collection, training) and resumed."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import helpers
import mpc_fakes
import numpy as np
import pytest

from ttompc.config import ConfigError
from ttompc.data.config import DataConfig
from ttompc.data.distributed import RankInfo
from ttompc.finetune import finetune, improves
from ttompc.finetune.collect import collect_iteration, expert_schedule, rollout_folder
from ttompc.finetune.config import ExplorationConfig, FinetuneConfig, LabelConfig, load_finetune_config
from ttompc.mpc.providers import ShiftProvider
from ttompc.mpc.settings import MPCSettings
from ttompc.policy.stats import NormStats
from ttompc.scenarios import get_scenario
from ttompc.seeding import rollout_seed

SHORT = mpc_fakes.FreeFlyerShort.name
RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def test_recipes_load_at_a_scale_that_can_work() -> None:
    zoo_ft = [p for p in sorted(RECIPES.glob("zoo/*-ft-*.yaml")) if "dagger:" in p.read_text()]  # not value legs
    paths = sorted(RECIPES.glob("*/*finetune.yaml")) + zoo_ft
    assert {p.parent.name for p in paths if p.name == "finetune.yaml"} == {"freeflyer", "quadrotor", "rpod", "generic"}
    for path in paths:
        cfg = load_finetune_config(path)
        assert cfg.dagger.iterations >= 1 and 0 < cfg.data.open_loop_fraction <= 1
        # at least the paper's first-iteration mix of labelled rollouts (>= 1,000 per iteration) and a
        # keep/reject decision on >= 100 selection problems (recipes/zoo/*-ft-tto-small: the record of the v1 models;
        # recipes/<scenario>/paper-finetune.yaml: the paper's own settings)
        if path.parent.name != "zoo" and path.stem != "paper-finetune":
            d = cfg.dagger
            assert d.collect.rollouts >= 1000 and d.eval.problems >= 50, path
            assert cfg.data.open_loop_fraction == 0.9, path
        # one process per core on these CPUs
        if path.name == "finetune.yaml" and path.parent.name != "generic":
            assert cfg.dagger.collect.workers == 1, path
        # one protocol per recipe: the training callback measures under dagger.eval's
        e, m = cfg.callbacks.eval_mpc, cfg.dagger.eval
        assert (e.protocol, e.mpc, e.settings) == (m.protocol, m.mpc, m.settings), path


def test_protocol_reaches_the_closed_loop_measurement(monkeypatch: pytest.MonkeyPatch) -> None:
    """dagger.eval is the one measurement of a fine-tuning: its protocol (with dagger.eval.mpc overrides) is what the
    keep/reject measurement runs with, and the training callback's; a bad setting is a config error."""
    import ttompc.evaluation.episodes as metrics
    from ttompc.finetune.loop import measure

    seen: dict[str, object] = {}

    def fake(planner, measurement, problems, **kwargs):  # type: ignore[no-untyped-def]
        seen.update(kwargs, measurement=measurement)
        return {"feasible_rate": 1.0}, []

    monkeypatch.setattr(metrics, "closed_loop_metrics", fake)
    recipe = RECIPES / "freeflyer" / "finetune.yaml"
    cfg = load_finetune_config(recipe)
    assert measure(cfg, object(), []) == {"feasible_rate": 1.0}  # type: ignore[arg-type]
    assert seen["measurement"] is cfg.dagger.eval  # the recipe's preset: recommended (the paper's with the value rtg)
    assert cfg.dagger.eval.settings == MPCSettings(
        end_horizon=None, rtg_mode="value", end_shift=True, rti=None, decoder="auto"
    )
    assert cfg.dagger.eval.horizons == [10]
    cfg = load_finetune_config(recipe, ["dagger.eval.protocol=zoo", "dagger.eval.mpc.mode=hard"])
    assert cfg.dagger.eval.settings == MPCSettings(end_horizon=30, mode="hard")
    assert cfg.callbacks.eval_mpc.settings == cfg.dagger.eval.settings  # named once, for every closed loop
    with pytest.raises(ConfigError, match="end_horizon"):
        load_finetune_config(recipe, ["dagger.eval.mpc.end_horizon=-1"])
    for key in ("callbacks.eval_mpc.protocol=zoo", "callbacks.eval_mpc.mpc.mode=hard"):
        with pytest.raises(ConfigError, match=r"names its MPC settings once, in dagger\.eval"):
            load_finetune_config(recipe, [key])
    with pytest.raises(ConfigError, match=r"dagger\.eval measures one horizon"):
        load_finetune_config(recipe, ["dagger.eval.horizons=[10,30]"])


def test_rollouts_take_the_settings_they_honour_and_refuse_the_others(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """DAgger's rollouts run under the resolved settings of dagger.eval (the end horizon must reach the rollouts,
    not only the measurement): both controllers get them whole, the learner's windows follow the end
    horizon; a decode schedule, which they cannot run, is refused in one line before anything runs."""
    import ttompc.finetune.collect as collect
    import ttompc.mpc.expert as expert
    import ttompc.mpc.loop as loop_module
    from ttompc.cli import main

    sc, planner = get_scenario(SHORT), mpc_fakes.tiny_planner()
    seen: list[tuple[int, MPCSettings]] = []
    real = loop_module.MPCController

    def spy(cls):  # type: ignore[no-untyped-def]
        def make(scenario, problem, provider, horizon, settings):  # type: ignore[no-untyped-def]
            seen.append((horizon, settings))
            return cls(scenario, problem, provider, horizon, settings)

        return make

    monkeypatch.setattr(expert, "ExpertController", spy(expert.ExpertController))  # the expert's
    monkeypatch.setattr(loop_module, "MPCController", spy(real))  # the learner's, an episode of run_mpc_batch
    overrides = ["dagger.eval.mpc.end_horizon=30", "dagger.eval.mpc.track=2.5"]
    settings = load_finetune_config(RECIPES / "freeflyer" / "finetune.yaml", overrides).dagger.eval.settings
    explore = ExplorationConfig(horizons=[5], windows=[0, 0])
    collect.collect_rollout(sc, planner, 0, 1, 5, explore, LabelConfig(kind="step", per_rollout=1), settings=settings)
    assert sorted(seen, key=lambda hs: hs[0]) == [(5, settings), (sc.n_steps, settings)]  # the learner, the expert
    everywhere = dataclasses.replace(settings, rti=True)  # RTI in every window but the expert's: its plans are labels
    problem = sc.sample(np.random.default_rng(0))
    assert not real(sc, problem, ShiftProvider(), sc.n_steps, everywhere).rti
    learner = real(sc, problem, ShiftProvider(), 5, settings)
    assert learner.window(sc.n_steps - 30).length == 30 and learner.window(0).length == 5
    with pytest.raises(ConfigError, match="decode_every=2"):
        collect.collect_rollouts(sc, planner, 0, [0], 5, explore, settings=MPCSettings(decode_every=2))
    recipe = str(RECIPES / "freeflyer" / "finetune.yaml")
    capsys.readouterr()  # what the rollout above printed (e.g. the solver kernel's status line) is not the command's
    assert main(["finetune", recipe, "--model", "no-such-model", "dagger.eval.mpc.decode_every=2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "decode_every=2" in err and "dagger.eval.mpc.decode_every=1" in err, err


def test_rollouts_run_real_time_iteration_for_the_learner_and_full_scp_for_the_expert(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Under ``rti=true`` the learner's windows after its first step are one subproblem each (plan reuse aside),
    while the expert, whose plans are the labels, still runs full SCP on every plan (to convergence or its budget)."""
    import ttompc.finetune.collect as collect
    import ttompc.mpc.expert as expert
    import ttompc.mpc.loop as loop_module

    sc, planner = get_scenario(SHORT), mpc_fakes.tiny_planner()
    rti: dict[str, bool] = {}  # whether each controller runs RTI (one rule, MPCSettings.rti_for: never the expert)
    plans: dict[str, list[tuple[int, bool]]] = {"learner": [], "expert": []}

    def spy(cls, who):  # type: ignore[no-untyped-def]
        class Spy(cls):  # type: ignore[misc, valid-type]
            def __init__(self, scenario, problem, provider, horizon, s):  # type: ignore[no-untyped-def]
                super().__init__(scenario, problem, provider, horizon, s)
                rti[who] = self.rti

            def plan(self, t, x):  # type: ignore[no-untyped-def]
                p = super().plan(t, x)
                plans[who].append((p.iterations, p.converged))
                return p

        return Spy

    monkeypatch.setattr(expert, "ExpertController", spy(expert.ExpertController, "expert"))
    monkeypatch.setattr(loop_module, "MPCController", spy(loop_module.MPCController, "learner"))
    explore = ExplorationConfig(horizons=[5], windows=[0, 0])
    rows = collect.collect_rollout(
        sc, planner, 0, 1, 5, explore, LabelConfig(kind="plan", per_rollout=3), settings=MPCSettings(rti=True)
    )
    assert rti["learner"] and not rti["expert"]
    assert len(plans["learner"]) == sc.n_steps and len(plans["expert"]) == 3 and len(rows) == 3
    assert plans["learner"][0][0] >= 1 and all(it <= 1 for it, _ in plans["learner"][1:]), plans["learner"]
    # full SCP solves, not one iteration: each converged or ran the scenario's whole budget (which happens on some
    # CPUs' rounding), and they are not all cut at one iteration
    budget = sc.scp.max_iters
    assert all(converged or it == budget for it, converged in plans["expert"]), plans["expert"]
    assert max(it for it, _ in plans["expert"]) > 1, plans["expert"]


@pytest.mark.parametrize(
    "key",
    ["max_steps", "max_epochs", "keep_checkpoints", "resume", "export_planner"],
)
def test_trainer_keys_dagger_would_ignore_are_rejected(key: str) -> None:
    with pytest.raises(ConfigError, match=key):
        load_finetune_config(RECIPES / "freeflyer" / "finetune.yaml", [f"trainer.{key}=1"])
    with pytest.raises(ConfigError, match="dagger_dirs"):
        load_finetune_config(None, ["data.dagger_dirs=[x]"])  # DAgger fills it: a value would be ignored
    cfg = load_finetune_config(None, ["trainer.num_sanity_val_steps=2", "trainer.checkpoint_every_n_steps=7"])
    assert (cfg.trainer.num_sanity_val_steps, cfg.trainer.checkpoint_every_n_steps) == (2, 7)
    assert load_finetune_config().trainer.out_dir == "runs/freeflyer-dagger"  # DAgger's own defaults


def test_keep_reject_rule() -> None:
    base = {"infeasible": 1.0, "cost_increment": 0.3}
    assert improves({"infeasible": 0.0, "cost_increment": 0.9}, base)[0]  # fewer infeasible runs first
    assert not improves({"infeasible": 2.0, "cost_increment": 0.1}, base)[0]
    assert improves({"infeasible": 1.0, "cost_increment": 0.2}, base)[0]
    assert not improves({"infeasible": 1.0, "cost_increment": 0.3}, base)[0]  # a tie is not an improvement
    nan = float("nan")
    assert not improves({"infeasible": 1.0, "cost_increment": nan}, {"infeasible": 1.0, "cost_increment": nan})[0]


def test_cli_takes_overrides_before_and_after_model(capsys: pytest.CaptureFixture[str]) -> None:
    from ttompc.cli import main

    recipe = str(RECIPES / "freeflyer" / "finetune.yaml")
    for argv in (["--model", "m", "dagger.iterations=7"], ["dagger.iterations=7", "--model", "m"]):
        assert main(["finetune", recipe, *argv, "--print-config"]) == 0
        assert json.loads(capsys.readouterr().out)["dagger"]["iterations"] == 7
    assert main(["finetune", recipe, "dagger.nope=1"]) == 2
    assert main(["finetune", recipe, "dagger.eval.protocol=zoo", "--print-config"]) == 0  # the resolved settings too
    printed = json.loads(capsys.readouterr().out)
    for section in (printed["dagger"]["eval"], printed["callbacks"]["eval_mpc"]):
        assert section["protocol"] == "zoo" and section["settings"]["end_horizon"] == 30


def test_expert_schedule_and_seeds() -> None:
    for s in range(20):
        mask = expert_schedule(np.random.default_rng(s), 100, ExplorationConfig())
        assert mask[-1] and 11 <= mask.sum() <= 75  # 1-3 windows, one covering the end
        end_only = expert_schedule(np.random.default_rng(s), 100, ExplorationConfig(windows=[1, 1]))
        start = int(np.argmax(end_only))
        assert end_only[start:].all() and 75 <= start <= 89 and 11 <= end_only.sum() <= 25
    assert rollout_seed(0, 0, 1) != rollout_seed(0, 1, 0) and rollout_seed(0, 2, 3) == rollout_seed(0, 2, 3)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ol") / "ds"
    helpers.tiny_dataset(out, SHORT, 4, (0.5, 0.5, 0.0), shard_size=4)
    return out


def _config(dataset: Path, run: Path) -> FinetuneConfig:
    cfg = FinetuneConfig()
    d = cfg.dagger
    d.iterations, d.steps_per_iteration = 2, 2
    d.exploration = ExplorationConfig(horizons=[10], windows=[1, 1], window_length=[5, 8])
    d.collect.rollouts, d.collect.shard_size, d.collect.workers, d.collect.val_fraction = 2, 1, 1, 0.0
    d.eval.problems, d.eval.horizons, d.eval.max_steps = 1, [5], 3
    cfg.data = DataConfig(paths=[str(dataset)], batch_size=4, shuffle_pool=8, context_length=10, open_loop_fraction=0.5)
    cfg.trainer.out_dir, cfg.trainer.val_check_interval, cfg.trainer.limit_val_batches = str(run), 2, 1
    cfg.trainer.log_every_n_steps, cfg.trainer.accelerator, cfg.trainer.checkpoint_every_n_steps = 1, "cpu", 1
    cfg.logger.kind = "csv"
    e = cfg.callbacks.eval_mpc  # the closed loop logged while it fine-tunes
    e.enabled, e.problems, e.horizons, e.max_steps = True, 1, [5], 3
    return cfg


class _Interrupt(KeyboardInterrupt):
    """Stands for Ctrl-C at a chosen point."""


def _mtimes(folder: Path) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_two_iterations_interrupted_and_resumed_keep_only_improvements(
    tmp_path: Path, dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import lightning as L
    import torch

    import ttompc.finetune.collect as collect
    import ttompc.finetune.loop as loop
    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.data.manifests import load_manifest
    from ttompc.policy import Planner
    from ttompc.training.module import SaveLastCheckpoint

    planner = mpc_fakes.tiny_planner()
    planner = Planner(planner.model, planner.scenario, NormStats.from_dict(load_manifest(dataset)["norm_stats"]))
    planner.extra["rtg_scale"] = 1.2  # the source's conditioning, as a published zoo model records it
    source = str(planner.save(tmp_path / "pretrained"))
    run = tmp_path / "run"
    cfg = _config(dataset, run)

    # The pretrained model is measured for real; the candidates get prescribed closed-loop results so the decision
    # is known: iteration 0 improves on the pretrained model (kept), iteration 1 does not improve on iteration 0.
    real_measure, measured = loop.measure, []
    increments = {0: 0.3, 1: 0.4}

    def measure(cfg: FinetuneConfig, planner: Planner, problems: list) -> dict[str, float]:
        metrics = real_measure(cfg, planner, problems)
        it = planner.extra.get("dagger_iteration", -1)
        measured.append(it)
        assert planner.rtg_scale == 1.2, it  # every candidate is measured at its source's conditioning
        if it >= 0:
            metrics.update(infeasible=0.0, cost_increment=increments[it])
        else:
            metrics.update(infeasible=0.0, cost_increment=0.5)
        return metrics

    monkeypatch.setattr(loop, "measure", measure)
    fits: list[str | None] = []
    original_fit = L.Trainer.fit

    def fit(self: L.Trainer, *args: object, ckpt_path: str | None = None, **kw: object) -> None:
        fits.append(ckpt_path)
        original_fit(self, *args, ckpt_path=ckpt_path, **kw)

    monkeypatch.setattr(L.Trainer, "fit", fit)

    # run 1: Ctrl-C while collecting iteration 1, after its shard 0 was written
    original_rollouts = collect.collect_rollouts

    def rollouts(scenario, planner, iteration, indices, *args, **kw):  # type: ignore[no-untyped-def]
        if iteration == 1 and 1 in indices:
            raise _Interrupt
        return original_rollouts(scenario, planner, iteration, indices, *args, **kw)

    monkeypatch.setattr(collect, "collect_rollouts", rollouts)
    with pytest.raises(_Interrupt):
        finetune(cfg, source)
    state = json.loads((run / "dagger_state.json").read_text())
    assert [r["iteration"] for r in state["completed"]] == [0] and state["completed"][0]["kept"]
    assert state["best"]["iteration"] == 0 and state["completed"][0]["global_step"] == 2
    it0 = _mtimes(run / "dagger" / "iter-000") | _mtimes(run / "checkpoints")
    shard0 = _mtimes(run / "dagger" / "iter-001")
    assert any("dagger-00000" in p.name for p in shard0) and not any("dagger-00001" in p.name for p in shard0)
    monkeypatch.setattr(collect, "collect_rollouts", original_rollouts)

    # run 2: Ctrl-C in iteration 1's training after step 3 (one step past the parent's 2)
    original_save = SaveLastCheckpoint.on_train_batch_end

    def save_then_stop(self: SaveLastCheckpoint, trainer: L.Trainer, *args: object) -> None:
        original_save(self, trainer, *args)
        if self.path.name == "iter-001.ckpt" and trainer.global_step == 3:
            raise _Interrupt

    monkeypatch.setattr(SaveLastCheckpoint, "on_train_batch_end", save_then_stop)
    fits.clear()
    with pytest.raises(KeyboardInterrupt):  # Lightning's sys.exit(1) on Ctrl-C is turned back into the interrupt
        finetune(cfg, source)
    assert fits == [str(run / "checkpoints" / "iter-000.ckpt")]  # iteration 1 starts from its kept parent
    assert {
        p: t for p, t in (_mtimes(run / "dagger" / "iter-000") | _mtimes(run / "checkpoints")).items() if p in it0
    } == it0
    assert {p: t for p, t in _mtimes(run / "dagger" / "iter-001").items() if p in shard0} == shard0  # not redone
    step = torch.load(run / "checkpoints" / "iter-001.ckpt", map_location="cpu", weights_only=True)["global_step"]
    assert step == 3
    monkeypatch.setattr(SaveLastCheckpoint, "on_train_batch_end", original_save)

    # run 3: continues iteration 1's training from step 3 (not from the parent, not from 0) and decides
    fits.clear()
    result = finetune(cfg, source)
    assert fits == [str(run / "checkpoints" / "iter-001.ckpt")]
    state = json.loads((run / "dagger_state.json").read_text())
    assert result.iterations == state["completed"] and [r["iteration"] for r in state["completed"]] == [0, 1]
    it1 = state["completed"][1]
    assert it1["global_step"] == 4 and it1["parent"] == 0 and not it1["kept"] and "0.4 vs 0.3" in it1["reason"]
    assert state["best"]["iteration"] == 0 == result.best_iteration
    assert measured.count(-1) == 1  # the pretrained model was measured once, not again on resume
    assert {"cost", "cost_increment", "feasible_rate", "infeasible"} <= set(state["baseline_metrics"])
    # the exported model is the kept iteration 0, not the rejected last one
    exported, kept = Planner.from_pretrained(run / "planner"), Planner.from_pretrained(state["best"]["planner"])
    assert exported.extra["dagger_iteration"] == 0 and exported.extra["dagger_kept"] == [0]
    protocol = state["protocol"]  # the measurement's settings, in the state file and the exported bundle
    assert protocol["name"] == cfg.dagger.eval.protocol and protocol["settings"]["end_horizon"] >= 0
    assert protocol["solver"]["chain"][0] == "riccati" and exported.extra["dagger_protocol"] == protocol
    hp = torch.load(run / "checkpoints" / "iter-001.ckpt", map_location="cpu", weights_only=True)["hyper_parameters"]
    assert hp["solver"] == protocol["solver"] == exported.extra["solver"]  # the checkpoint records what DAgger solved
    assert exported.rtg_scale == 1.2
    for (name, a), b in zip(exported.model.state_dict().items(), kept.model.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=name)
    rejected = Planner.from_pretrained(it1["planner"])
    pairs = zip(rejected.model.parameters(), exported.model.parameters(), strict=True)
    assert any(not torch.equal(a, b) for a, b in pairs)
    logs = "".join(p.read_text() for p in sorted((run / "logs").glob("session-*/metrics.csv")))
    assert "dagger/kept" in logs and "dagger/cost_increment" in logs
    assert "mpc/cost_increment" in logs  # callbacks.eval_mpc: the closed loop during each iteration's training
    # its iterations' records carry the compute each phase took
    assert all(set(r["seconds"]) == {"collect", "train", "measure"} for r in state["completed"])

    # the learning curve: every model measured on both plants, paired against the pretrained one; resumable
    from ttompc.finetune.curve import curve_figure, measure_curve

    curve = measure_curve(run, [str(dataset)], problems=1, horizon=5, max_steps=3)
    assert [r["iteration"] for r in curve] == [-1, 0, 1]
    # max_steps=3 cuts every episode short: no goal reached, no cost to pair with the pretrained one's, all counted
    assert curve[0]["nominal"]["vs_pretrained"]["n"] == 0 and curve[0]["nominal"]["truncated"] == 1
    assert curve[0]["nominal"]["feasible_rate"] == 0 and curve[0]["labels"] == 0
    assert curve[2]["rollouts"] == 2 * cfg.dagger.collect.rollouts and curve[2]["labels"] >= curve[1]["labels"] > 0
    assert all(r["perturbed"]["feasible_rate"] >= 0 for r in curve)
    again = measure_curve(run, [str(dataset)], problems=1, horizon=5, max_steps=3)  # nothing re-measured
    assert json.dumps(again, sort_keys=True) == json.dumps(curve, sort_keys=True)
    assert curve_figure([run], tmp_path / "curve.png").stat().st_size > 0
    robust = measure_curve(run, [str(dataset)], problems=1, horizon=5, max_steps=3, robust_blend=0.9)
    assert [r["iteration"] for r in robust] == [-1, 0, 1] and (run / "curve-robust.json").is_file()
    assert json.loads((run / "curve.json").read_text()) == json.loads(json.dumps(curve))  # its own file
    assert curve_figure([run], tmp_path / "both.png").stat().st_size > 0
    import matplotlib.image

    two = matplotlib.image.imread(curve_figure([run, run], tmp_path / "two.png"))  # a row per run (scenario)
    assert two.shape[0] == 2 * matplotlib.image.imread(tmp_path / "both.png").shape[0]

    # a finished run re-run does nothing new
    before = _mtimes(run / "dagger") | _mtimes(run / "checkpoints")
    fits.clear()
    assert finetune(cfg, source).iterations == result.iterations and fits == []
    assert _mtimes(run / "dagger") | _mtimes(run / "checkpoints") == before

    # the DataModule reads the DAgger shards back: source, iteration, consistent expert labels
    folder = run / "dagger" / "iter-000"
    dm = TrajectoryDataModule(
        DataConfig(
            paths=[str(dataset)],
            dagger_dirs=[str(folder)],
            batch_size=6,
            shuffle_pool=6,
            context_length=40,
            open_loop_fraction=0.0,
        )
    )
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert set(batch["source"].tolist()) == {2}
    assert {int(p) // 10_000_000 for p in batch["problem_id"]} == {0}
    st = dm.stats
    S = st.denormalize("states", batch["states"].double()).numpy()
    A = st.denormalize("actions", batch["target_actions"].double()).numpy()
    S_next = st.denormalize("states", batch["target_next_states"].double()).numpy()
    sc = get_scenario(SHORT)
    np.testing.assert_allclose(S_next, sc.step(None, 0, S, A), atol=2e-5)  # label = f(x_t, u*_t)
    # the paper's mix: 9:1 open loop at the first iteration ("grow"), or fixed
    for share in ("fixed", "grow"):
        mix = DataConfig(
            paths=[str(dataset)],
            dagger_dirs=[str(folder)],
            context_length=40,
            open_loop_fraction=0.9,
            closed_loop_share=share,
        )
        mixed = TrajectoryDataModule(mix)
        mixed.setup("fit")
        assert mixed.open_loop_fraction() == pytest.approx(0.9)

    # a lost shard is recollected identically (seeded rollouts), by the rank that owns it
    import datasets

    rows = datasets.load_dataset("parquet", data_files=[str(folder / "train" / "dagger-00001.parquet")], split="train")
    assert set(rows["iteration"]) == {0} and set(rows["source"]) == {"dagger"} and rows["status"][0].startswith("H=10;")
    (folder / "meta" / "shard-00001.json").unlink()
    shards = rollout_folder(folder, sc, cfg.dagger.collect.rollouts, cfg.dagger.collect.shard_size)
    src = run / "source-planner"
    assert collect_iteration(cfg.dagger, sc, 0, src, shards, RankInfo(0, 2)) == []
    assert collect_iteration(cfg.dagger, sc, 0, src, shards, RankInfo(1, 2)) == [1]
    assert shards.done(1)
    redo = datasets.load_dataset("parquet", data_files=[str(folder / "train" / "dagger-00001.parquet")], split="train")
    np.testing.assert_array_equal(np.asarray(redo["target_actions"]), np.asarray(rows["target_actions"]))


def test_curve_figure_draws_a_row_per_run_from_its_curve_files(tmp_path: Path) -> None:
    """The DAgger curve's figure from curve files alone (the slow test above draws one from a real run): a row per
    run, whichever methods were measured; a run with no measured curve is named."""
    import matplotlib.image

    from ttompc.finetune.curve import CURVE_FILES, curve_figure

    def record(iteration: int) -> dict[str, object]:
        plant = {"vs_pretrained": {"mean": 0.01 * iteration, "se": 0.002, "n": 3}, "feasible_rate": 0.9}
        return {"iteration": iteration, "imitation_loss": 0.1 * (iteration + 2), "nominal": plant, "perturbed": plant}

    def run(name: str, files: list[str]) -> Path:
        folder = tmp_path / name
        (folder / "source-planner").mkdir(parents=True)
        (folder / "source-planner" / "config.json").write_text(json.dumps({"scenario": {"name": SHORT}}))
        for file in files:
            (folder / file).write_text(json.dumps([record(i) for i in (-1, 0, 1)]))
        return folder

    plain, both = run("plain", ["curve.json"]), run("both", list(CURVE_FILES.values()))
    one = matplotlib.image.imread(curve_figure([plain], tmp_path / "one.png"))
    two = matplotlib.image.imread(curve_figure([plain, both], tmp_path / "two.png"))
    assert two.shape[1] == one.shape[1] and two.shape[0] == 2 * one.shape[0]
    with pytest.raises(FileNotFoundError, match="unmeasured has no measured curve"):
        curve_figure([plain, run("unmeasured", [])], tmp_path / "none.png")
    assert not (tmp_path / "none.png").exists()


def test_run_folder_of_another_fine_tuning_is_refused(tmp_path: Path, dataset: Path) -> None:
    from ttompc.finetune import FinetuneError

    run = tmp_path / "run"
    run.mkdir()
    state = {"source": "a", "seed": 0, "baseline_metrics": {}, "best": {}, "completed": []}
    (run / "dagger_state.json").write_text(json.dumps(state))
    cfg = _config(dataset, run)
    with pytest.raises(FinetuneError, match="fine-tunes 'a', not 'b'"):
        finetune(cfg, "b")
    cfg.dagger.seed = 5
    with pytest.raises(FinetuneError, match=r"dagger\.seed=0"):
        finetune(cfg, "a")
    (run / "dagger_state.json").write_text(json.dumps({"source": "a", "seed": 0, "completed": []}))
    with pytest.raises(FinetuneError, match="older ttompc"):
        finetune(cfg, "a")


def test_inputs_that_do_not_belong_together_are_refused_before_anything_is_written(
    tmp_path: Path, dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before: a model, recipe and dataset that do not belong together were refused at the first training step, after
    the pretrained model's measurement and a whole collection. Now nothing is written, measured or collected."""
    import helpers

    import ttompc.finetune.loop as loop
    from ttompc.data.manifests import load_manifest
    from ttompc.evaluation.measurement import Measurement
    from ttompc.finetune import FinetuneError
    from ttompc.policy import Planner

    def spent(*args: object, **kwargs: object) -> None:
        raise AssertionError("measured or collected before the inputs were checked")

    monkeypatch.setattr(Measurement, "problem_set", spent)
    monkeypatch.setattr(loop, "collect_iteration", spent)
    tiny = mpc_fakes.tiny_planner()
    own = NormStats.from_dict(load_manifest(dataset)["norm_stats"])
    other = NormStats(own.mean, {k: 2 * v for k, v in own.std.items()})
    models = {
        "own": Planner(tiny.model, tiny.scenario, own).save(tmp_path / "own"),
        "other-stats": Planner(tiny.model, tiny.scenario, other).save(tmp_path / "other-stats"),
        "toy": helpers.tiny_toy_planner().save(tmp_path / "toy"),
    }
    run = tmp_path / "run"
    for model, data, match in [
        ("own", {"scenario": "quadrotor"}, f"{models['own']} is a {SHORT} model but the recipe is for quadrotor"),
        ("own", {"paths": [str(tmp_path / "nope")]}, "dataset folder .*nope does not exist.*the model was trained on"),
        ("toy", {}, f"holds {SHORT} trajectories but the model .* is a toy model"),
        ("other-stats", {}, r"normalisation statistics of .* \(states\) differ from those of the model"),
    ]:
        cfg = _config(dataset, run)
        for key, value in data.items():
            setattr(cfg.data, key, value)
        with pytest.raises(FinetuneError, match=match):
            finetune(cfg, str(models[model]))
        assert not run.exists()


def test_expert_labels_with_plan_reuse_are_the_re_solved_optimum(monkeypatch: pytest.MonkeyPatch) -> None:
    """After every step the expert acted in, the visited state is the expert's own prediction and its plan's tail is
    the label of the next state (plan reuse, when that plan met the SCP's stopping rule): at every such state a
    re-solve (what the expert did before) reaches the same objective, and each reuse saves a solve. The controls
    themselves may move within the optimal face of the L1 fuel cost (an interior-point re-solve returns another
    point of equal cost)."""
    import ttompc.mpc.loop as loop_module
    from ttompc.finetune.collect import collect_rollout

    sc, planner = get_scenario(SHORT), mpc_fakes.tiny_planner()
    exploration = ExplorationConfig(horizons=[10], windows=[2, 2], window_length=[8, 8])
    checked, solves = [], []
    real_plan, real_solve = loop_module.MPCController.plan, loop_module.solve_scp

    def objective(X: np.ndarray, U: np.ndarray) -> float:
        return sc.mpc.fuel * sc.cost(U) + sc.mpc.end * float(np.linalg.norm(X[-1] - ctrl_problem[0].goal))

    ctrl_problem: list = []

    def plan(self, t, x):
        step = real_plan(self, t, x)
        if step.reused:
            ctrl_problem[:] = [self.problem]
            again = self.solve(self.window(t), step.X, step.U, None)
            assert again.success
            checked.append((objective(step.X, step.U), objective(again.X, again.U)))
        return step

    def count(*args, **kw):
        solves.append(1)
        return real_solve(*args, **kw)

    monkeypatch.setattr(loop_module.MPCController, "plan", plan)
    monkeypatch.setattr(loop_module, "solve_scp", count)
    counts = {}
    for name, reuse in (("cold", False), ("reuse", True)):
        solves.clear()
        collect_rollout(sc, planner, 0, 1, 5, exploration, settings=MPCSettings(reuse=reuse))
        counts[name] = len(solves) - len(checked)
    assert len(checked) >= 5  # after the expert steps whose plan met the stopping rule
    reused, resolved = np.array(checked).T
    assert np.all(reused <= resolved * (1 + 1e-5))  # a reused tail is never worse than a re-solve from it ...
    np.testing.assert_allclose(reused, resolved, rtol=1e-4)  # ... which may stop 1e-4 short of it (the SCP's rule)
    assert counts["cold"] - counts["reuse"] >= len(checked)


def test_label_schedule_draws_distinct_steps_or_none() -> None:
    from ttompc.finetune.collect import label_schedule

    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert label_schedule(rng, 20, 0).all() and label_schedule(rng, 20, 25).all()
    assert rng.bit_generator.state == state  # every step labelled: no draw, so such rollouts keep their seeds
    for k in (1, 5, 19):
        assert label_schedule(np.random.default_rng(k), 20, k).sum() == k
    with pytest.raises(ValueError, match="per_rollout"):
        LabelConfig(per_rollout=-1)
    with pytest.raises(ValueError, match="kind"):
        LabelConfig(kind="suffix")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="late"):
        LabelConfig(late=-1.0)


def test_late_labels_favour_the_end_of_the_episode() -> None:
    """``labels.late`` tilts the draw toward late steps (weights e^{late·t/(N-1)}): still k distinct steps, the same
    draw as before when 0, and under late = 2 the last quarter is labelled far more often than the first."""
    from ttompc.finetune.collect import label_schedule

    assert (
        label_schedule(np.random.default_rng(3), 40, 6, 0.0) == label_schedule(np.random.default_rng(3), 40, 6)
    ).all()
    counts = {late: np.zeros(40) for late in (0.0, 2.0)}
    for seed in range(400):
        for late in counts:
            mask = label_schedule(np.random.default_rng(seed), 40, 6, late)
            assert mask.sum() == 6
            counts[late] += mask
    uniform, tilted = counts[0.0], counts[2.0]
    assert 0.8 < uniform[30:].sum() / uniform[:10].sum() < 1.25
    assert tilted[30:].sum() > 3 * tilted[:10].sum()


def _expert_from_scratch(sc: object, problem: object, t: int, x: np.ndarray) -> np.ndarray:
    """The expert's plan at (t, x_t) solved without any earlier plan: REL over [t, N) from x_t, then the full-horizon
    soft-mode SCP from it."""
    from ttompc.mpc.loop import MPCController
    from ttompc.mpc.providers import RemainingREL, ShiftProvider

    shift = ShiftProvider()
    expert = MPCController(sc, problem, shift, problem.n_steps)  # type: ignore[arg-type, attr-defined]
    shift.reset(sc, problem, 0.0)  # type: ignore[arg-type]
    rel = RemainingREL()(sc, problem, t, x)  # type: ignore[arg-type]
    shift.reset_plan(rel.X, rel.U)
    return expert.plan(t, x).U  # type: ignore[no-any-return]


def test_subsampled_and_plan_labels_match_the_expert_from_scratch() -> None:
    """Labels on a subset of steps (NaN elsewhere), plan rows that continue the visited prefix with the expert's plan,
    both from the same visited trajectory and the same expert solves; every-step labels agree with a from-scratch solve
    (cost within 1e-6); the DataModule masks the unlabelled steps."""
    from ttompc.finetune.collect import _sample_problem, collect_rollout

    sc = get_scenario(SHORT)
    planner = mpc_fakes.tiny_planner()
    explore = ExplorationConfig(horizons=[5], windows=[0, 0])
    every = collect_rollout(sc, planner, 0, 3, 7, explore, LabelConfig(kind="plan"))  # the paper's every step
    (sub,) = collect_rollout(sc, planner, 0, 3, 7, explore, LabelConfig(kind="step", per_rollout=4))
    plans = collect_rollout(sc, planner, 0, 3, 7, explore, LabelConfig(kind="plan", per_rollout=4))
    labelled = np.flatnonzero(np.isfinite(sub["target_actions"]).all(axis=1))
    assert len(labelled) == 4 and sub["status"].endswith("labels=4")
    full = every[-1]
    T = int(full["status"].rsplit("plan_from=", 1)[1])
    np.testing.assert_array_equal(sub["states"][:T], full["states"][:T])  # labels do not change what is visited
    starts = [int(r["status"].rsplit("plan_from=", 1)[1]) for r in plans]
    assert set(starts) <= set(labelled) and len(starts) >= 2  # a labelled step whose expert solve failed has no row
    problem = _sample_problem(sc, np.random.default_rng(rollout_seed(7, 0, 3)))[0]
    for t, row in zip(starts, plans, strict=True):
        ta = np.asarray(row["target_actions"])
        assert np.isnan(ta[:t]).all() and np.isfinite(ta[t:]).all()
        np.testing.assert_allclose(row["states"][: t + 1], sub["states"][: t + 1], rtol=0, atol=1e-12)
        np.testing.assert_allclose(row["actions"][:t], sub["actions"][:t], rtol=0, atol=1e-12)
        np.testing.assert_allclose(ta[t], sub["target_actions"][t], rtol=0, atol=1e-12)  # the same expert solve
        np.testing.assert_allclose(row["target_next_states"][t:], row["states"][t + 1 :], rtol=0, atol=1e-9)
        # the plan's rtg runs on with the plan's stage costs from the learner's value at t
        assert row["rtg"][t] == pytest.approx(sub["rtg"][t])
        assert row["rtg"][-1] - row["rtg"][t] == pytest.approx(sc.cost(ta[t:-1]), rel=1e-9)
        miss = np.linalg.norm(np.asarray(row["states"][-1]) - sc.model_goal(problem))
        assert miss < np.linalg.norm(
            np.asarray(sub["states"][-1]) - sc.model_goal(problem)
        )  # the expert's plan ends nearer
    expert_rtg = collect_rollout(sc, planner, 0, 3, 7, explore, LabelConfig(kind="plan", per_rollout=4, rtg="expert"))
    for t, row, other in zip(starts, plans, expert_rtg, strict=True):  # the same rows but for the rtg from t on
        np.testing.assert_array_equal(row["actions"], other["actions"])
        np.testing.assert_array_equal(row["rtg"][:t], other["rtg"][:t])
        togo = -np.cumsum(sc.stage_cost(np.asarray(row["actions"])[t:])[::-1])[::-1]  # the plan's own cost-to-go
        np.testing.assert_allclose(other["rtg"][t:], togo, rtol=1e-12, atol=0)
        assert other["rtg"][t] == pytest.approx(-sc.cost(np.asarray(row["actions"])[t:]))
    X = sc.from_model_states(problem, np.asarray(sub["states"]))
    by_start = {int(r["status"].rsplit("plan_from=", 1)[1]): r for r in every}
    for t in (3, 11):  # every-step labels: the full-horizon optimum within 1e-6 of the cost, where the learner was
        label = sc.cost(np.asarray(by_start[t]["actions"])[t:])
        assert label == pytest.approx(sc.cost(_expert_from_scratch(sc, problem, t, X[t])), rel=1e-6)


def test_robust_blend_reaches_rollouts_measurement_and_callback(monkeypatch: pytest.MonkeyPatch) -> None:
    """dagger.eval.robust_blend > 0 makes the learner of every rollout and the keep/reject measurement R-TTO-MPC
    (their terminal targets blended by it), and the training callback's measurement too; 0 keeps TTO-MPC."""
    import ttompc.mpc.methods as methods
    from ttompc.evaluation.episodes import closed_loop_metrics
    from ttompc.evaluation.measurement import Measurement
    from ttompc.finetune.collect import collect_rollouts

    blends: list[float] = []
    real = methods.terminal_term

    def spy(settings, blend=0.0, planner=None):  # type: ignore[no-untyped-def]
        blends.append(blend)
        return real(settings, blend, planner)

    monkeypatch.setattr(methods, "terminal_term", spy)
    sc, planner = get_scenario(SHORT), mpc_fakes.tiny_planner()
    explore = ExplorationConfig(horizons=[5], windows=[0, 0], window_length=[4, 6])
    labels = LabelConfig(kind="step", per_rollout=2)
    for blend in (0.0, 0.9):
        blends.clear()
        collect_rollouts(sc, planner, 0, [0, 1], 5, explore, labels, robust_blend=blend)
        assert blends == [blend, blend]
    m = Measurement(problems=1, robust_blend=0.9, max_steps=2)
    blends.clear()
    closed_loop_metrics(planner, m, m.problem_set(sc))
    assert blends == [0.9]
    cfg = load_finetune_config(RECIPES / "quadrotor" / "finetune.yaml")
    assert cfg.dagger.eval.robust_blend == cfg.callbacks.eval_mpc.robust_blend == 0.95
    cfg = load_finetune_config(RECIPES / "quadrotor" / "finetune.yaml", ["dagger.eval.robust_blend=0"])
    assert cfg.callbacks.eval_mpc.robust_blend == 0.0
    with pytest.raises(ConfigError, match=r"names its MPC settings once"):
        load_finetune_config(RECIPES / "quadrotor" / "finetune.yaml", ["callbacks.eval_mpc.robust_blend=0.5"])
    with pytest.raises(ValueError, match="robust_blend"):
        Measurement(robust_blend=1.0)


def test_rollouts_feed_the_learners_rtg_mode() -> None:
    """Under rtg_mode=value the learner of a rollout is fed its model's cost-to-go, so its row's rtg is no ledger
    (rtg_(t+1) − rtg_t = c(u_t)); a model without a value output runs the ledger under the same settings."""
    import torch

    from ttompc.finetune.collect import collect_rollouts
    from ttompc.policy import ModelConfig, Planner, TrajectoryGPT

    sc = get_scenario(SHORT)
    plain = mpc_fakes.tiny_planner()
    torch.manual_seed(1)
    valued_model = TrajectoryGPT(ModelConfig(**{**plain.model.cfg.__dict__, "value_width": 8}))
    valued_model.load_state_dict(plain.model.state_dict(), strict=False)
    valued = Planner(valued_model.eval(), sc, plain.stats)
    explore = ExplorationConfig(horizons=[5], windows=[0, 0], window_length=[4, 6])
    labels = LabelConfig(kind="step", per_rollout=2)
    settings = MPCSettings(rtg_mode="value")

    def ledger_gap(planner: Planner) -> float:
        ((row,),) = collect_rollouts(sc, planner, 0, [0], 5, explore, labels, settings=settings)
        return float(np.max(np.abs(np.diff(row["rtg"]) - sc.stage_cost(np.asarray(row["actions"]))[:-1])))

    assert ledger_gap(plain) < 1e-6
    assert ledger_gap(valued) > 1e-3


@pytest.mark.parametrize("rounding", [0.0, 1e-7])
def test_lockstep_rollouts_equal_lone_rollouts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, rounding: float
) -> None:
    """Rollouts run in lockstep (one batched transformer rollout per step for all) are the rollouts each gives alone:
    the same problems, H, expert windows and labelled steps; each row carries its own learner's conditioning
    (rtg_0 = −κ·J_REL of its problem, then its own executed costs); the visited trajectory equals the lone one up to
    the rounding of a batched rollout over its first steps. Later the closed loop amplifies that rounding: with a
    tiny untrained model the window SCPs take failed steps and trust-region decisions that a 1e-17 change of the
    warm start can flip (measured on one CPU in float64: rollouts equal to 1e-17, the first control to 2e-5, the
    state 3 steps on to 1e-3, the episode costs to 8%), so the rest after the first step is compared through the
    cost, loosely; also when the batch rounds otherwise than the lone rollout (``rounding``, as another CPU's); a
    chunk never crosses a shard."""
    from ttompc.finetune.collect import _sample_problem, chunks, collect_rollout, collect_rollouts

    sc = get_scenario(SHORT)
    planner = mpc_fakes.tiny_planner()
    mpc_fakes.perturb_batched_rollouts(monkeypatch, rounding)
    explore = ExplorationConfig(horizons=[5, 8], windows=[0, 1], window_length=[4, 6])
    labels = LabelConfig(kind="step", per_rollout=4)
    together = collect_rollouts(sc, planner, 2, [0, 1, 2], 11, explore, labels)
    assert len(together) == 3
    for index, (row,) in enumerate(together):
        (alone,) = collect_rollout(sc, planner, 2, index, 11, explore, labels)
        assert row["problem_id"] == alone["problem_id"] and row["seed"] == alone["seed"]
        assert row["status"].split(";")[:2] == alone["status"].split(";")[:2]  # H and the expert's windows
        np.testing.assert_array_equal(np.isfinite(row["target_actions"]), np.isfinite(alone["target_actions"]))
        rel = _sample_problem(sc, np.random.default_rng(rollout_seed(11, 2, index)))[1]
        assert row["rtg"][0] == pytest.approx(-planner.rtg_scale * rel.cost, rel=1e-6)
        np.testing.assert_allclose(np.diff(row["rtg"]), sc.stage_cost(np.asarray(row["actions"]))[:-1], atol=1e-7)
        # the first window's control lies on an L1 face: with other rounding it moves by ~1e-4 (states reach ~2.6);
        # later states part further (measured at 1e-7 of rounding: 6.5e-3 two steps on)
        np.testing.assert_array_equal(row["states"][0], alone["states"][0])
        np.testing.assert_allclose(row["states"][1], alone["states"][1], rtol=0, atol=3e-3)
        assert row["cost"] == pytest.approx(alone["cost"], rel=0.25)
    folder = rollout_folder(tmp_path, sc, 23, 10)
    assert chunks(folder, [0, 2], 4) == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9], [20, 21, 22]]


def test_datamodule_masks_unlabelled_steps(tmp_path: Path, dataset: Path) -> None:
    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.finetune.collect import collect_rollout

    sc = get_scenario(SHORT)
    planner = mpc_fakes.tiny_planner()
    explore = ExplorationConfig(horizons=[5], windows=[0, 0])
    rows = collect_rollout(sc, planner, 0, 1, 0, explore, LabelConfig(kind="plan", per_rollout=3))
    folder = rollout_folder(tmp_path / "iter-000", sc, 1, 1)
    folder.write(0, {"train": rows, "val": rows})
    data = DataConfig(
        paths=[str(dataset)],
        dagger_dirs=[str(tmp_path / "iter-000")],
        batch_size=3,
        shuffle_pool=3,
        context_length=sc.n_steps,
        open_loop_fraction=0.0,
    )
    dm = TrajectoryDataModule(data)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    starts = {int(r["status"].rsplit("plan_from=", 1)[1]) for r in rows}
    got = {int(np.argmax(m)) for m in batch["mask"].numpy()}
    assert got <= starts and len(got) >= 1
    for m in batch["mask"].numpy():
        t = int(np.argmax(m))
        assert not m[:t].any() and m[t:].all()
    assert torch_finite(batch["target_actions"]) and torch_finite(batch["target_next_states"])


def test_plan_rows_carry_the_costates_of_the_expert_solve(monkeypatch: pytest.MonkeyPatch) -> None:
    """A plan row from step t carries the costates of the expert's solve from x_t (``Expert.plan_costates``), in the
    model representation (``model_costates``) at steps t+1..N and NaN up to t: a solved plan's are its solve's, a
    reused plan's (plan reuse in an expert window) those of the solve that produced it, shifted; they are ∂J*/∂x of
    the plan's cost-to-go (central differences of re-solves; the quadrotor's cost is quadratic). NaN throughout where
    the plan misses the goal (λ would be the gradient of the priced miss). The conic backends give the same costates
    as the Riccati kernel on the same rollouts."""
    from ttompc.data.schema import model_costates, problem_from_row
    from ttompc.finetune import collect
    from ttompc.mpc.expert import ExpertController
    from ttompc.mpc.loop import MPCController
    from ttompc.mpc.providers import ShiftProvider
    from ttompc.scenarios.base import Window

    sc, planner = get_scenario("quadrotor"), mpc_fakes.tiny_planner("quadrotor")
    solved, reused = {}, set()
    real_solve, real_plan = ExpertController.solve, ExpertController.plan

    def solve(self, window, *args, **kw):  # type: ignore[no-untyped-def]
        res = solved[window.start] = real_solve(self, window, *args, **kw)
        return res

    def plan(self, t, x):  # type: ignore[no-untyped-def]
        e = real_plan(self, t, x)
        if e.reused:
            reused.add(t)
        return e

    monkeypatch.setattr(ExpertController, "solve", solve)
    monkeypatch.setattr(ExpertController, "plan", plan)
    explore = ExplorationConfig(horizons=[5], windows=[1, 1], window_length=[3, 4], end_window=False)
    rows = collect.collect_rollout(sc, planner, 0, 2, 5, explore, LabelConfig(kind="plan", per_rollout=2))
    p = problem_from_row(sc, rows[0])
    N, by_start, kinds = p.n_steps, {}, {}
    for row in rows:
        t = int(row["status"].rsplit("plan_from=", 1)[1])
        lam = by_start[t] = np.asarray(row["costates"])
        assert lam.shape == (N + 1, sc.state_dim) and np.isnan(lam[: t + 1]).all()
        if np.max(np.abs(np.asarray(row["states_opt"])[-1] - p.goal)) > sc.scp.feas_tol:
            assert np.isnan(lam).all()
            kinds[t] = "miss"
            continue
        assert np.isfinite(lam[t + 1 :]).all()
        if t in reused:
            np.testing.assert_array_equal(lam[t + 1 :], by_start[t - 1][t + 1 :])
            kinds[t] = "reused"
        else:
            ref = np.full((N + 1, sc.state_dim), np.nan)
            ref[t:] = solved[t].costates / sc.mpc.fuel
            np.testing.assert_allclose(lam, model_costates(sc, p, ref), rtol=1e-12, atol=0)
            kinds[t] = "solved"
    assert set(kinds.values()) == {"solved", "reused", "miss"}
    t = min(s for s, kind in kinds.items() if kind == "solved")
    row = next(r for r in rows if r["status"].endswith(f"plan_from={t}"))
    k, X, U = t + 1, np.asarray(row["states_opt"], np.float64), np.asarray(row["actions"], np.float64)
    expert = MPCController(sc, p, ShiftProvider(), N)

    def cost_to_go(x: np.ndarray) -> float:
        X0 = X[k:].copy()
        X0[0] = x
        res = expert.solve(Window(k, N - k, N), X0, U[k:], None)
        return sc.cost(res.U)

    units = sc.state_units()
    fd = np.array(
        [
            (cost_to_go(X[k] + 1e-4 * u * e) - cost_to_go(X[k] - 1e-4 * u * e)) / (2e-4 * u)
            for e, u in zip(np.eye(sc.state_dim), units, strict=True)
        ]
    )
    np.testing.assert_allclose(row["costates"][k], fd, rtol=0.02, atol=1e-3 * np.abs(fd).max())
    monkeypatch.undo()
    conic = collect.collect_rollout(
        sc, planner, 0, 2, 5, explore, LabelConfig(kind="plan", per_rollout=2), settings=MPCSettings(backend="conic")
    )
    assert len(conic) == len(rows)
    for r, c in zip(rows, conic, strict=True):
        lam, lam_conic = np.asarray(r["costates"]), np.asarray(c["costates"])
        assert r["status"] == c["status"] and np.array_equal(np.isnan(lam), np.isnan(lam_conic))
        np.testing.assert_allclose(lam_conic, lam, rtol=1e-2, atol=1e-3 * np.nanmax(np.abs(lam), initial=1.0))


def test_dagger_shards_with_and_without_costates_load(tmp_path: Path, dataset: Path) -> None:
    """Plan rows written with their costates and shards written before the column (read as NaN) load through the
    DataModule together; ``grad_mask`` is 1 exactly at the steps whose costates are finite (none in the old shards)
    and ``value_grad`` is finite, 0 elsewhere."""
    import pyarrow.parquet as pq

    from ttompc.data.datamodule import TrajectoryDataModule
    from ttompc.finetune.collect import collect_rollouts

    sc, planner = get_scenario(SHORT), mpc_fakes.tiny_planner()
    explore = ExplorationConfig(horizons=[5], windows=[0, 0])
    new, old = collect_rollouts(sc, planner, 0, [0, 1], 2, explore, LabelConfig(kind="plan", per_rollout=3))
    dirs = [tmp_path / "iter-000", tmp_path / "iter-001"]
    for d, rows in zip(dirs, (new, old), strict=True):
        rollout_folder(d, sc, 1, 1).write(0, {"train": rows, "val": rows})
    for f in dirs[1].glob("*/*.parquet"):
        pq.write_table(pq.read_table(f).drop_columns(["costates"]), f)  # as written before the column
    N = sc.n_steps
    expected = {
        (r["problem_id"], int(r["status"].rsplit("plan_from=", 1)[1])): np.isfinite(r["costates"][:N]).all(1)
        for r in new
    }
    expected |= {(r["problem_id"], int(r["status"].rsplit("plan_from=", 1)[1])): np.zeros(N, bool) for r in old}
    assert any(m.any() for m in expected.values()) and any(np.isfinite(r["costates"]).any() for r in old)
    data = DataConfig(
        paths=[str(dataset)],
        dagger_dirs=[str(d) for d in dirs],
        batch_size=3,
        shuffle_pool=3,
        context_length=N,
        open_loop_fraction=0.0,
    )
    dm = TrajectoryDataModule(data)
    dm.setup("fit")
    seen = set()
    for batch in dm.dagger_val_dataloader():
        for pid, mask, grad_mask, grad in zip(
            *(batch[k].numpy() for k in ("problem_id", "mask", "grad_mask", "value_grad")), strict=True
        ):
            key = (int(pid), int(np.argmax(mask)))
            seen.add(key)
            np.testing.assert_array_equal(grad_mask.astype(bool), expected[key])
            assert np.isfinite(grad).all() and not grad[~expected[key]].any()
    assert seen == set(expected)


def torch_finite(x: object) -> bool:
    import torch

    return bool(torch.isfinite(x).all())  # type: ignore[arg-type]


def test_a_share_of_rollouts_runs_on_the_perturbed_plant() -> None:
    """``dagger.collect.perturbed``: each rollout draws its plant from its own seed; a perturbed rollout visits other
    states than the same rollout on the exact plant (same problem, H and windows), labels them, and says so in its
    status; a share of 0 is the exact plant for every rollout."""
    from ttompc.finetune.collect import collect_rollouts, rollout_plant

    sc = get_scenario(SHORT)
    draws = [not rollout_plant(sc, rollout_seed(3, 0, r), 0.5).noise.nominal for r in range(200)]
    assert 70 < sum(draws) < 130  # about half
    assert all(rollout_plant(sc, rollout_seed(3, 0, r), 0.0).noise.nominal for r in range(20))
    planner = mpc_fakes.tiny_planner()
    explore = ExplorationConfig(horizons=[5], windows=[0, 0], window_length=[4, 6], end_window=False)
    labels = LabelConfig(kind="step", per_rollout=3)
    ((exact,),), ((disturbed,),) = (
        collect_rollouts(sc, planner, 0, [0], 5, explore, labels, perturbed=p) for p in (0, 1)
    )
    assert exact["status"].endswith("plant=nominal;labels=3") and "plant=perturbed" in disturbed["status"]
    assert exact["problem_id"] == disturbed["problem_id"]
    np.testing.assert_array_equal(exact["states"][0], disturbed["states"][0])
    assert np.abs(np.asarray(exact["states"][1:]) - np.asarray(disturbed["states"][1:])).max() > 1e-4
    labelled = np.isfinite(np.asarray(disturbed["target_actions"])).all(axis=1)
    assert labelled.sum() == 3


def test_the_paper_scale_recipe_loads_at_the_authors_scale() -> None:
    """recipes/quadrotor/finetune.yaml: 8 iterations of 4,000 rollouts, aggregated (every iteration's folder is
    trained on), the expert finishing each episode, a share on the perturbed plant, under protocol=recommended."""
    cfg = load_finetune_config(RECIPES / "quadrotor" / "finetune.yaml")
    d = cfg.dagger
    assert (d.iterations, d.collect.rollouts) == (8, 4000) and d.exploration.end_window
    assert 0 < d.collect.perturbed < 1 and d.eval.protocol == "recommended" and d.eval.problems >= 50
    assert cfg.data.closed_loop_share == "grow"
