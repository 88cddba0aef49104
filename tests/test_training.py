"""Training: the loss goes down, a tiny run writes logger files and a planner bundle, resumes from last.ckpt, and
checkpoint / bundle reproduce the trained model's rollouts exactly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, Dataset

from ttompc.config import to_container
from ttompc.policy import Planner
from ttompc.policy.stats import NormStats
from ttompc.scenarios import get_scenario
from ttompc.solvers.backends import backend_chain, default_trust_norm
from ttompc.training.config import OptimConfig, TrainConfig, load_train_config
from ttompc.training.module import TrajectoryTransformerModule
from ttompc.training.run import train

STEPS = 12  # the toy scenario's horizon


def toy_arrays(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Trajectories of the toy double integrator under a saturated PD law towards a random goal."""
    sc = get_scenario("toy")
    rng = np.random.default_rng(seed)
    S, A, G = np.zeros((n, STEPS + 1, 6)), np.zeros((n, STEPS, 3)), np.zeros((n, STEPS, 6))
    for i in range(n):
        p = sc.sample(rng)
        x = p.x0
        S[i, 0] = x
        for k in range(STEPS):
            u = np.clip(0.4 * (p.goal[:3] - x[:3]) - 0.9 * x[3:], -1.0, 1.0)
            x = sc.step(p, k, x, u)
            A[i, k], S[i, k + 1] = u, x
        G[i] = p.goal
    cost = np.abs(A).sum(-1)
    rtg = -np.cumsum(cost[:, ::-1], axis=1)[:, ::-1]
    ctg = np.zeros_like(rtg)
    return {"states": S, "actions": A, "goals": G, "rtg": rtg[..., None], "ctg": ctg[..., None]}


class ToyDataset(Dataset):
    def __init__(self, arrays: dict[str, np.ndarray], stats: NormStats) -> None:
        f = lambda k, x: torch.as_tensor(stats.normalize(k, x), dtype=torch.float32)  # noqa: E731
        S = arrays["states"]
        self.items = {
            "states": f("states", S[:, :-1]),
            "actions": f("actions", arrays["actions"]),
            "goals": f("goals", arrays["goals"]),
            "rtg": f("rtg", arrays["rtg"]),
            "ctg": f("ctg", arrays["ctg"]),
            "target_actions": f("actions", arrays["actions"]),
            "target_next_states": f("states", S[:, 1:]),
        }
        n = S.shape[0]
        self.items["timesteps"] = torch.arange(STEPS).expand(n, -1).clone()
        self.items["mask"] = torch.ones(n, STEPS)
        self.items["mask"][::3, -2:] = 0.0  # some padded steps

    def __len__(self) -> int:
        return self.items["states"].shape[0]

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v[i] for k, v in self.items.items()}


class ToyDataModule(L.LightningDataModule):
    """Stand-in for ``TrajectoryDataModule`` with the same batch contract and ``stats``/``scenario_name``."""

    scenario_name = "toy"

    def __init__(self, n: int = 64, batch_size: int = 16) -> None:
        super().__init__()
        self.n, self.batch_size = n, batch_size
        self.stats: NormStats | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.stats is None:
            arrays = toy_arrays(self.n)
            self.stats = NormStats.from_arrays({**arrays, "states": arrays["states"][:, :-1]})
            split = self.n * 3 // 4
            self.train_set = ToyDataset({k: v[:split] for k, v in arrays.items()}, self.stats)
            self.val_set = ToyDataset({k: v[split:] for k, v in arrays.items()}, self.stats)

    def use_stats(self, stats: NormStats) -> None:
        self.stats = stats
        split = self.n * 3 // 4
        arrays = toy_arrays(self.n)
        self.train_set = ToyDataset({k: v[:split] for k, v in arrays.items()}, stats)
        self.val_set = ToyDataset({k: v[split:] for k, v in arrays.items()}, stats)

    def train_dataloader(self) -> DataLoader:
        return DataLoader(
            self.train_set,
            batch_size=self.batch_size,
            shuffle=True,
            generator=torch.Generator().manual_seed(0),
        )

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size)


def tiny_config(out_dir: Path, *overrides: str) -> TrainConfig:
    recipe = Path(__file__).resolve().parents[1] / "recipes" / "freeflyer" / "tiny.yaml"
    return load_train_config(
        recipe,
        [
            f"trainer.out_dir={out_dir}",
            "model.n_embd=32",
            "model.n_layer=2",
            "model.n_head=2",
            f"model.max_steps={STEPS}",
            "trainer.checkpoint_every_n_steps=3",
            "trainer.log_every_n_steps=1",
            "trainer.val_check_interval=3",
            "trainer.limit_val_batches=1",
            "optim.warmup_steps=2",
            *overrides,
        ],
    )


def test_huber_loss_is_mse_inside_delta_and_linear_outside() -> None:
    """optim.huber_delta: the same loss as MSE where every error is within delta; an outlier's gradient is capped at
    2·delta per element (MSE's grows with the error); masked steps count in neither."""
    from ttompc.training.module import masked_mse

    target = torch.zeros(2, 3, 2)
    mask = torch.tensor([[1.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    small = torch.full((2, 3, 2), 0.3, requires_grad=True)
    assert masked_mse(small, target, mask, 1.0).item() == pytest.approx(masked_mse(small, target, mask).item())
    big = torch.zeros(2, 3, 2)
    big[0, 0, 0], big[0, 2, 1] = 50.0, 1e6  # an outlier on a labelled step, a huge error on a masked one
    big.requires_grad_(True)
    loss = masked_mse(big, target, mask, 1.0)
    assert loss.item() == pytest.approx((2 * 50.0 - 1.0) / 6)  # 3 labelled steps x 2 dims
    loss.backward()
    assert big.grad is not None
    assert big.grad[0, 0, 0].item() == pytest.approx(2.0 / 6) and big.grad[0, 2, 1].item() == 0.0
    with pytest.raises(ValueError, match="huber_delta"):
        OptimConfig(huber_delta=0.0)


@pytest.mark.slow  # ~50 s on the loaded 2-core machine: make test-all / CI
def test_loss_decreases_on_synthetic_data() -> None:
    torch.manual_seed(0)
    dm = ToyDataModule(n=64, batch_size=32)
    dm.setup("fit")
    cfg = tiny_config(Path("unused"), "model.dropout=0.0", "optim.lr=3e-3", "optim.schedule=constant")
    module = TrajectoryTransformerModule(
        to_container(cfg.model), to_container(cfg.optim), "toy", "0.1", dm.stats.to_dict()
    )
    optim = module.configure_optimizers()
    opt, sched = optim["optimizer"], optim["lr_scheduler"]["scheduler"]
    batch = next(iter(dm.train_dataloader()))
    losses = []
    for _ in range(40):
        loss = module._losses(batch)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses


def test_tiny_run_logs_resumes_and_exports(tmp_path: Path, wandb_offline: Path) -> None:
    out = tmp_path / "run"
    first = train(tiny_config(out, "trainer.max_steps=4", "logger.kind=wandb"), ToyDataModule())
    assert first.start_step == 0 and first.global_step == 4
    assert first.last_checkpoint.is_file() and (out / "checkpoints" / "step00000003.ckpt").is_file()
    assert list((out / "wandb").glob("offline-run-*/run-*.wandb")), "no offline wandb run files"
    assert list((out / "plots").glob("val_trajectories_*.png")), "no trajectory plot"
    assert (out / "planner" / "model.safetensors").is_file()
    assert "val/loss" in first.metrics

    # Same out_dir, larger budget: continues from step 4, never from zero.
    second = train(tiny_config(out, "trainer.max_steps=7", "logger.kind=wandb"), ToyDataModule())
    assert second.start_step == 4 and second.global_step == 7
    assert torch.load(second.last_checkpoint, weights_only=True)["global_step"] == 7
    assert len(list((out / "wandb").glob("offline-run-*"))) >= 1

    # The checkpoint alone and the exported bundle give the same planner, bit for bit.
    sc = get_scenario("toy")
    problems = [sc.sample(np.random.default_rng(s)) for s in range(3)]
    a = Planner.from_pretrained(second.last_checkpoint)
    b = Planner.from_pretrained(out / "planner")
    assert json.loads((out / "planner" / "config.json").read_text())["extra"]["global_step"] == 7
    Xa, Ua = a.warm_start(problems, rtg0=[-2.0, -3.0, -4.0])
    Xb, Ub = b.warm_start(problems, rtg0=[-2.0, -3.0, -4.0])
    assert Xa.shape == (3, STEPS + 1, 6) and Ua.shape == (3, STEPS, 3)
    np.testing.assert_array_equal(Xa, Xb)
    np.testing.assert_array_equal(Ua, Ub)
    np.testing.assert_allclose(Xa[:, 0], np.stack([p.x0 for p in problems]))  # back in the optimisation frame

    # Checkpoint and bundle record the solver path of the run's backend (the protocol's auto): chain and norm.
    resolved = {"backend": "auto", "chain": backend_chain("auto", sc), "trust_norm": default_trust_norm("auto", sc)}
    assert torch.load(second.last_checkpoint, weights_only=True)["hyper_parameters"]["solver"] == resolved
    assert a.extra["solver"] == b.extra["solver"] == resolved


def test_init_from_continues_published_weights(tmp_path: Path) -> None:
    """A fresh run with init_from starts from the source's weights and statistics (a stacked model here), not from a
    new initialisation; an architecture that differs from the source's is a one-line config error."""
    from ttompc.config import ConfigError

    common = ("logger.kind=none", "model.layout=stacked", "trainer.checkpoint_every_n_steps=100")
    src = train(tiny_config(tmp_path / "src", "trainer.max_steps=4", *common), ToyDataModule(n=32))
    assert src.planner_dir is not None
    source = Planner.from_pretrained(src.planner_dir)
    assert source.model.cfg.layout == "stacked"
    # one step at a vanishing learning rate: the continued weights are the source's (a fresh init is far from them)
    tiny_lr = ("trainer.max_steps=1", "optim.lr=1e-12", "optim.warmup_steps=0", *common)
    cont = train(tiny_config(tmp_path / "cont", *tiny_lr, f"init_from={src.planner_dir}"), ToyDataModule(n=32))
    fresh = train(tiny_config(tmp_path / "fresh", *tiny_lr), ToyDataModule(n=32))
    want = source.model.state_dict()
    got = Planner.from_pretrained(cont.planner_dir).model.state_dict()  # type: ignore[arg-type]
    new = Planner.from_pretrained(fresh.planner_dir).model.state_dict()  # type: ignore[arg-type]
    assert all(torch.allclose(got[k], want[k], atol=1e-7) for k in want)
    assert max((new[k] - want[k]).abs().max().item() for k in want) > 1e-3
    with pytest.raises(ConfigError, match=r"model\.n_embd=64 differs from init_from's 32"):
        train(
            tiny_config(tmp_path / "bad", *tiny_lr, "model.n_embd=64", f"init_from={src.planner_dir}"), ToyDataModule()
        )


class _CrashAt(L.Callback):
    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_end(self, trainer: L.Trainer, *args: object) -> None:
        if trainer.global_step == self.step:
            raise RuntimeError("simulated crash")


def test_crashed_run_resumes_from_exception_checkpoint(tmp_path: Path) -> None:
    """A run that dies between periodic checkpoints resumes where it died, not at the last periodic save."""
    out = tmp_path / "crash"
    cfg = tiny_config(out, "trainer.max_steps=8", "logger.kind=none", "trainer.checkpoint_every_n_steps=100")
    with pytest.raises(RuntimeError, match="simulated crash"):
        train(cfg, ToyDataModule(n=32), callbacks=[_CrashAt(5)])
    assert not (out / "checkpoints" / "last.ckpt").exists()
    res = train(cfg, ToyDataModule(n=32))
    assert res.start_step == 5 and res.global_step == 8


def test_csv_logger_and_cosine_schedule(tmp_path: Path) -> None:
    out = tmp_path / "csv"
    res = train(
        tiny_config(
            out,
            "trainer.max_steps=3",
            "logger.kind=csv",
            "optim.schedule=cosine",
            "trainer.export_planner=false",
        ),
        ToyDataModule(n=32),
    )
    assert res.global_step == 3 and res.planner_dir is None
    metrics = (out / "logs" / "session-0" / "metrics.csv").read_text()
    assert "train/loss" in metrics and "val/loss" in metrics
    # a resumed session logs next to the first one instead of overwriting its metrics.csv
    cfg = tiny_config(
        out, "trainer.max_steps=5", "logger.kind=csv", "optim.schedule=cosine", "trainer.export_planner=false"
    )
    assert train(cfg, ToyDataModule(n=32)).global_step == 5
    assert (out / "logs" / "session-0" / "metrics.csv").read_text() == metrics
    assert "train/loss" in (out / "logs" / "session-1" / "metrics.csv").read_text()


def test_planner_bundle_roundtrip(tmp_path: Path, toy, toy_stats: NormStats) -> None:
    from ttompc.policy import ModelConfig, TrajectoryGPT

    torch.manual_seed(0)
    planner = Planner(
        TrajectoryGPT(ModelConfig(n_embd=32, n_layer=1, n_head=2, max_steps=STEPS)),
        toy,
        toy_stats,
        recipe={"note": "test"},
    )
    planner.save(tmp_path / "p")
    loaded = Planner.from_pretrained(tmp_path / "p")
    problems = [toy.sample(np.random.default_rng(1))]
    X, U = planner.warm_start(problems, -2.0)
    np.testing.assert_array_equal(U, loaded.warm_start(problems, -2.0)[1])
    assert X.dtype == np.float64 and np.array_equal(X[0, 0], problems[0].x0)  # the SCP's fixed state, exactly
    meta = json.loads((tmp_path / "p" / "config.json").read_text())
    assert meta["scenario"] == {"name": "toy", "version": "0.1", "spec": "conftest:ToyScenario"}
    assert meta["recipe"] == {"note": "test"}
    meta["scenario"]["version"] = "9.9"
    (tmp_path / "p" / "config.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"v9\.9"):
        Planner.from_pretrained(tmp_path / "p")
    assert Planner.from_pretrained(tmp_path / "p", check_version=False).scenario.name == "toy"


def test_train_cli_reports_config_errors(capsys: pytest.CaptureFixture[str]) -> None:
    from ttompc.cli import main

    recipe = "recipes/freeflyer/tiny.yaml"
    root = Path(__file__).resolve().parents[1]
    assert main(["train", str(root / recipe), "optim.lrr=1"]) == 2
    assert "optim.lrr" in capsys.readouterr().err
    assert main(["train", "--print-config", str(root / recipe), "optim.lr=0.5"]) == 0
    assert json.loads(capsys.readouterr().out)["optim"]["lr"] == 0.5


@pytest.mark.slow  # two spawned training processes, ~40 s: make test-all / CI
def test_ddp_spawn_two_cpu_processes(tmp_path: Path) -> None:
    """Spawned workers train; the launching process still reports the workers' step and exports the planner."""
    out = tmp_path / "ddp_spawn"
    cfg = tiny_config(
        out,
        "trainer.max_steps=2",
        "logger.kind=none",
        "trainer.devices=2",
        "trainer.strategy=ddp_spawn",
        "trainer.accelerator=cpu",
    )
    res = train(cfg, ToyDataModule(n=32, batch_size=8))
    assert res.global_step == 2
    assert torch.load(res.last_checkpoint, weights_only=True)["global_step"] == 2
    assert (out / "planner" / "model.safetensors").is_file()


DDP_SCRIPT = """
import sys
import conftest  # registers the toy scenario
from pathlib import Path
from test_training import ToyDataModule, tiny_config
from ttompc.training.run import train

res = train(tiny_config(Path(sys.argv[1]), "trainer.max_steps=2", "logger.kind=csv", "trainer.devices=2",
                        "trainer.strategy=ddp", "trainer.accelerator=cpu"), ToyDataModule(n=32, batch_size=8))
print("RESULT", res.global_step, flush=True)
"""


@pytest.mark.slow  # two training processes, ~40 s: make test-all / CI
def test_ddp_two_cpu_processes(tmp_path: Path) -> None:
    """``trainer.strategy=ddp``: Lightning re-launches the script as a second process (gloo on localhost)."""
    script = tmp_path / "ddp_run.py"
    script.write_text(DDP_SCRIPT)
    tests_dir = Path(__file__).resolve().parent
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tests_dir), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "ddp")],
        cwd=tests_dir.parent,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count("RESULT 2") == 2, proc.stdout  # both ranks finished at step 2
    assert torch.load(tmp_path / "ddp" / "checkpoints" / "last.ckpt", weights_only=True)["global_step"] == 2


PRETRAIN_RECIPES = sorted((Path(__file__).resolve().parents[1] / "recipes").glob("*/paper-pretrain.yaml"))


@pytest.mark.parametrize("cuda", [False, True], ids=["cpu", "cuda-faked"])
def test_paper_recipes_pick_the_gpu_when_present_and_bf16_on_either(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cuda: bool
) -> None:
    """The paper-size recipes train on a CUDA GPU when one is visible and on the CPU otherwise, in bf16 autocast on
    both where they compute bf16 natively (``precision: auto``). No GPU is needed: CUDA availability and bf16 support
    are faked, and only the Trainer is built (nothing runs on it)."""
    from dataclasses import replace

    from lightning.pytorch.accelerators import CPUAccelerator, CUDAAccelerator
    from lightning.pytorch.plugins.precision import MixedPrecision

    from ttompc.training.run import build_trainer

    monkeypatch.setattr("ttompc.training.precision.read_cpu_flags", lambda: frozenset({"avx2", "amx_bf16"}))
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: True)
    if cuda:
        monkeypatch.setattr(CUDAAccelerator, "is_available", staticmethod(lambda: True))
        monkeypatch.setattr("lightning.fabric.accelerators.cuda.num_cuda_devices", lambda: 1)
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
        monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert {p.parent.name for p in PRETRAIN_RECIPES} == {"freeflyer", "quadrotor", "rpod"}
    for path in PRETRAIN_RECIPES:
        cfg = load_train_config(path, [f"trainer.out_dir={tmp_path}"])
        trainer = build_trainer(replace(cfg.trainer, max_steps=1), cfg.optim, tmp_path, None)
        assert isinstance(trainer.accelerator, CUDAAccelerator if cuda else CPUAccelerator), path
        plugin = trainer.precision_plugin
        assert isinstance(plugin, MixedPrecision) and plugin.precision == "bf16-mixed", path
        assert plugin.device == ("cuda" if cuda else "cpu"), path
    # the schema default (a recipe that says nothing) fits the machine too
    assert TrainConfig().trainer.precision == "auto"


def test_bf16_mixed_cpu_run_keeps_fp32_weights(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """bf16 autocast on the CPU trains (finite loss) and keeps fp32 master weights, so checkpoints
    and exported planners are the same fp32 models as from a 32-true run. ``precision: auto`` on a CPU with native
    bf16 (faked flags) resolves to it; the recipe keeps ``auto``, the checkpoint and the bundle record what ran."""
    monkeypatch.setattr("ttompc.training.precision.read_cpu_flags", lambda: frozenset({"avx2", "avx512_bf16"}))
    torch.manual_seed(0)
    res = train(
        tiny_config(tmp_path / "run", "trainer.max_steps=3", "trainer.precision=auto", "logger.kind=none"),
        ToyDataModule(n=32),
    )
    assert res.global_step == 3 and np.isfinite(res.metrics["train/loss"])
    ckpt = torch.load(res.last_checkpoint, map_location="cpu", weights_only=True)
    assert ckpt["hyper_parameters"]["recipe"]["trainer"]["precision"] == "auto"
    assert ckpt["precision"] == "bf16-mixed"
    weights = ckpt["state_dict"]
    assert all(w.dtype == torch.float32 for w in weights.values() if w.is_floating_point())
    planner = Planner.from_pretrained(res.planner_dir, get_scenario("toy"))
    assert next(planner.model.parameters()).dtype == torch.float32
    assert planner.extra["precision"] == "bf16-mixed"  # the exported bundle's record
