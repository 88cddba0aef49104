"""``trainer.precision: auto`` (``ttompc.training.precision``): bf16 autocast where the training device computes
bf16 natively, fp32 elsewhere; explicit values pass through; the recipe accepts ``auto`` and names the key of a bad
value. The tiny run that records the resolved precision is ``test_bf16_mixed_cpu_run_keeps_fp32_weights``
(tests/test_training.py)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from ttompc.config import ConfigError
from ttompc.training.config import TrainConfig, load_train_config
from ttompc.training.precision import NATIVE_BF16_FLAGS, read_cpu_flags, resolve_precision

ROOT = Path(__file__).resolve().parents[1]
# /proc/cpuinfo flags (abridged) of an AMD EPYC with AVX2 only, and of an Intel Xeon with AVX512-BF16 and AMX
AVX2_ONLY = frozenset({"fpu", "sse4_2", "avx", "avx2", "fma", "f16c", "sha_ni"})
AMX = frozenset({"fpu", "sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile", "amx_int8"})
# the recipes that said bf16-mixed before they said ``auto``
AUTO_RECIPES = [
    *(f"{s}/pretrain.yaml" for s in ("freeflyer", "quadrotor", "rpod", "generic")),
    *(f"{s}/paper-pretrain.yaml" for s in ("freeflyer", "quadrotor", "rpod")),
    "zoo/freeflyer-tto-v2.yaml",
]


def test_auto_on_the_cpu_follows_its_native_bf16_flags() -> None:
    assert resolve_precision("auto", cuda=False, cpu_flags=AVX2_ONLY) == "32-true"
    assert resolve_precision("auto", cuda=False, cpu_flags=AMX) == "bf16-mixed"
    assert resolve_precision("auto", cuda=False, cpu_flags={"avx2", "avx512_bf16"}) == "bf16-mixed"  # e.g. Zen 4
    assert resolve_precision("auto", cuda=False, cpu_flags=()) == "32-true"  # no /proc/cpuinfo
    # trainer.accelerator=cpu trains on the CPU even beside a GPU
    assert resolve_precision("auto", accelerator="cpu", cuda=True, cuda_bf16=True, cpu_flags=AVX2_ONLY) == "32-true"
    assert resolve_precision("auto", accelerator="cpu", cuda=True, cuda_bf16=False, cpu_flags=AMX) == "bf16-mixed"


def test_auto_on_cuda_follows_the_gpu(monkeypatch: pytest.MonkeyPatch) -> None:
    assert resolve_precision("auto", cuda=True, cuda_bf16=True, cpu_flags=AVX2_ONLY) == "bf16-mixed"
    assert resolve_precision("auto", accelerator="gpu", cuda=True, cuda_bf16=False, cpu_flags=AMX) == "32-true"
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: not including_emulation)
    assert resolve_precision("auto", accelerator="cuda", cuda=True, cpu_flags=AVX2_ONLY) == "bf16-mixed"

    # a fork-based strategy must not find CUDA initialised: the GPU is not asked, fp32
    def initialises_cuda(including_emulation: bool = True) -> bool:
        raise AssertionError("asked the GPU before a fork")

    monkeypatch.setattr(torch.cuda, "is_bf16_supported", initialises_cuda)
    assert resolve_precision("auto", strategy="ddp_fork", cuda=True, cpu_flags=AMX) == "32-true"
    # another accelerator (mps, tpu) is not guessed for
    assert resolve_precision("auto", accelerator="mps", cuda=False, cpu_flags=AMX) == "32-true"


@pytest.mark.parametrize("value", ["32-true", "bf16-mixed", "16-mixed", "64-true", "bf16-true", "32"])
def test_explicit_values_pass_through(value: str) -> None:
    for flags in (AVX2_ONLY, AMX):
        for cuda in (False, True):
            assert resolve_precision(value, cuda=cuda, cuda_bf16=cuda, cpu_flags=flags) == value


def test_cpu_flags_come_from_cpuinfo(tmp_path: Path) -> None:
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(
        "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu avx avx2 fma\n\n"
        "processor\t: 1\nmodel name\t: AMD EPYC\nflags\t\t: fpu avx avx2 fma\nbugs\t\t: sysret_ss_attrs\n"
    )
    assert read_cpu_flags(cpuinfo) == {"fpu", "avx", "avx2", "fma"}
    assert read_cpu_flags(tmp_path / "missing") == frozenset()
    # with no flags given, this machine's are read
    expected = "bf16-mixed" if read_cpu_flags() & NATIVE_BF16_FLAGS else "32-true"
    assert resolve_precision("auto", accelerator="cpu") == expected


def test_recipes_accept_auto_and_name_the_key_of_a_bad_value() -> None:
    assert TrainConfig().trainer.precision == "auto"
    for rel in AUTO_RECIPES:
        assert load_train_config(ROOT / "recipes" / rel).trainer.precision == "auto", rel
    assert load_train_config(None, ["trainer.precision=32-true"]).trainer.precision == "32-true"
    with pytest.raises(ConfigError, match=r"trainer\.precision.*'bf16-fast'.*'auto'"):
        load_train_config(None, ["trainer.precision=bf16-fast"])


@pytest.mark.parametrize(("flags", "expected"), [(AVX2_ONLY, "32-true"), (AMX, "bf16-mixed")], ids=["avx2", "amx"])
def test_the_trainer_runs_the_resolved_precision(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, flags: frozenset[str], expected: str
) -> None:
    from ttompc.training.run import build_trainer

    monkeypatch.setattr("ttompc.training.precision.read_cpu_flags", lambda: flags)
    cfg = TrainConfig()
    trainer = build_trainer(replace(cfg.trainer, accelerator="cpu", max_steps=1), cfg.optim, tmp_path, None)
    assert trainer.precision == expected
