"""Training-step speed on CPU: tokens per second of one full step (forward + backward + clipping + AdamW) of the real
``TrajectoryTransformerModule`` loss, per model size, precision, compilation, thread count and batch size, with the
validation loss reached at equal steps by the candidate default vs fp32, and the token-layout axis: the paper's
interleaved layout (5 tokens per step) against the stacked one (1 token per step) at equal width and depth, reported
as trajectories per CPU-second (``layouts`` in the result; ``--layout-study`` runs only that comparison).

Every case keeps its own model, optimiser and batch; the cases are timed round-robin (one step each per round,
``--reps`` rounds, median), so a load change on this shared machine hits all of them alike and the ratios against
the baseline (fp32 eager, 2 threads, same size, batch 32; 8 for 11M) stay meaningful. Batches are synthetic tensors
of the real shapes (100 steps: 500 tokens per trajectory interleaved, 100 stacked); step speed does not depend on the
values.

Modes: ``fp32`` eager; ``bf16`` = ``torch.autocast(bfloat16)`` as Lightning's ``precision: bf16-mixed``; ``bf16mm`` =
fp32 with ``torch.set_float32_matmul_precision("medium")`` (oneDNN matmuls take bf16 inputs, everything else fp32);
``compile`` / ``compile-bf16`` = ``torch.compile`` of the transformer (compilation time reported apart).

The loss check trains the 0.6M model twice from the same initialisation on the same batches (fp32 and the
candidate), plus fp32 from a second initialisation for the seed-to-seed spread, and reports the validation loss on a
fixed held-out set. Data: ``--data FOLDER`` (a generated dataset, read by ``TrajectoryDataModule``), otherwise
free-flyer trajectories generated here (sampled problems, smooth random thrust, exact dynamics; no solver).

    python bench/train_speed.py            # writes bench/results/train_speed.json and prints one JSON line
    python bench/train_speed.py --layout-study --loss-steps 0    # the layout comparison only (a few CPU-minutes)
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from record import Machine, load_average, result_path, write_result

from ttompc.policy.config import TOKENS_PER_STEP
from ttompc.policy.stats import NormStats
from ttompc.scenarios import get_scenario
from ttompc.training.module import TrajectoryTransformerModule

RESULTS = result_path("train_speed")
SIZES = {"tiny": (64, 2, 4), "0.6M": (128, 3, 4), "1.8M": (192, 4, 6), "11M": (384, 6, 6)}  # n_embd, n_layer, n_head
N_STEPS = 100
BASE = ("fp32", 2)  # mode, threads of the baseline every case of a size is compared with (its smallest batch)


@dataclass
class Case:
    size: str
    mode: str
    threads: int
    batch: int
    times: list[float] = field(default_factory=list)
    cpu_times: list[float] = field(default_factory=list)  # process CPU seconds (all threads): less load-sensitive
    compile_s: float | None = None
    layout: str = "interleaved"

    @property
    def name(self) -> str:
        return f"{self.size}/{self.layout}/{self.mode}/t{self.threads}/b{self.batch}"

    @property
    def tokens(self) -> int:
        """Tokens in one batch."""
        return self.batch * N_STEPS * TOKENS_PER_STEP[self.layout]


def build(
    size: str, seed: int, lr: float = 1e-3, layout: str = "interleaved"
) -> tuple[TrajectoryTransformerModule, torch.optim.Optimizer]:
    """The real module (dropout 0.1, attention dropout 0 as the recipes) and its own AdamW."""
    d, n_layer, n_head = SIZES[size]
    sc = get_scenario("freeflyer")
    keys = {"states": sc.state_dim, "actions": sc.control_dim, "goals": sc.state_dim, "rtg": 1, "ctg": 1}
    stats = {"mean": {k: [0.0] * n for k, n in keys.items()}, "std": {k: [1.0] * n for k, n in keys.items()}}
    torch.manual_seed(seed)
    model = {"n_embd": d, "n_layer": n_layer, "n_head": n_head, "dropout": 0.1, "attn_dropout": 0.0, "layout": layout}
    mod = TrajectoryTransformerModule(model, {"lr": lr, "warmup_steps": 0}, "freeflyer", sc.version, stats)
    mod.train()
    return mod, mod.configure_optimizers()["optimizer"]


def random_batch(batch: int, seed: int) -> dict[str, torch.Tensor]:
    """Synthetic batch with the training contract's shapes (free-flyer: 6 states, 3 controls, 100 steps)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    B, L = batch, N_STEPS
    return {
        "states": r(B, L, 6),
        "actions": r(B, L, 3),
        "goals": r(B, L, 6),
        "rtg": r(B, L, 1),
        "ctg": r(B, L, 1),
        "timesteps": torch.arange(L).expand(B, L).contiguous(),
        "target_actions": r(B, L, 3),
        "target_next_states": r(B, L, 6),
        "mask": torch.ones(B, L),
    }


def precision_ctx(mode: str) -> Any:
    return torch.autocast("cpu", dtype=torch.bfloat16) if mode.endswith("bf16") else nullcontext()


def train_step(mod: TrajectoryTransformerModule, opt: torch.optim.Optimizer, batch: dict, mode: str) -> float:
    """One optimiser step as Lightning does it: loss under the precision context, backward, clip 1.0, AdamW."""
    torch.set_float32_matmul_precision("medium" if mode == "bf16mm" else "highest")
    with precision_ctx(mode):
        loss = mod._losses(batch)[0]
    loss.backward()
    torch.nn.utils.clip_grad_norm_(mod.parameters(), 1.0)
    opt.step()
    opt.zero_grad(set_to_none=True)
    return float(loss.detach())


def speed(cases: list[Case], reps: int) -> None:
    state = {}
    for i, c in enumerate(cases):
        torch.set_num_threads(c.threads)
        mod, opt = build(c.size, seed=0, layout=c.layout)
        if c.mode.startswith("compile"):
            mod.model = torch.compile(mod.model)
        batch = random_batch(c.batch, seed=i)
        t0 = time.perf_counter()
        train_step(mod, opt, batch, c.mode)  # warm-up (and compilation)
        if c.mode.startswith("compile"):
            c.compile_s = time.perf_counter() - t0
            train_step(mod, opt, batch, c.mode)  # the first backward recompiles nothing, but allocates
        state[c.name] = (mod, opt, batch)
    for _ in range(reps):
        for c in cases:
            torch.set_num_threads(c.threads)
            mod, opt, batch = state[c.name]
            t0, c0 = time.perf_counter(), time.process_time()
            train_step(mod, opt, batch, c.mode)
            c.times.append(time.perf_counter() - t0)
            c.cpu_times.append(time.process_time() - c0)
    torch.set_float32_matmul_precision("highest")


# ------------------------------------------------------------------------------------------------ loss check
def generated_arrays(n: int, seed: int) -> dict[str, np.ndarray]:
    """Free-flyer trajectories: sampled problems, smooth random Δv (an AR(1) process at the control scale), exact
    dynamics; rtg = −cost-to-go, ctg = keep-out violations to go (the datasets' definitions)."""
    sc = get_scenario("freeflyer")
    rng = np.random.default_rng(seed)
    scale = np.asarray(sc.control_scale)
    S, A, G = np.zeros((n, N_STEPS + 1, 6)), np.zeros((n, N_STEPS, 3)), np.zeros((n, N_STEPS, 6))
    rtg, ctg = np.zeros((n, N_STEPS)), np.zeros((n, N_STEPS))
    for i in range(n):
        p = sc.sample(rng)
        u = np.zeros((N_STEPS, 3))
        for k in range(1, N_STEPS):
            u[k] = 0.9 * u[k - 1] + 0.3 * scale * rng.standard_normal(3)
        X = sc.rollout(p, u)
        S[i], A[i], G[i] = X, u, sc.model_goal(p)
        rtg[i] = -np.cumsum(sc.stage_cost(u)[::-1])[::-1]
        ctg[i] = np.cumsum(sc.violations(p, X[:-1])[::-1])[::-1]
    return {"states": S, "actions": A, "goals": G, "rtg": rtg[..., None], "ctg": ctg[..., None]}


def tensors(a: dict[str, np.ndarray], stats: NormStats) -> dict[str, torch.Tensor]:
    f = lambda k, x: torch.as_tensor(stats.normalize(k, x), dtype=torch.float32)  # noqa: E731
    n = a["actions"].shape[0]
    return {
        "states": f("states", a["states"][:, :-1]),
        "actions": f("actions", a["actions"]),
        "goals": f("goals", a["goals"]),
        "rtg": f("rtg", a["rtg"]),
        "ctg": f("ctg", a["ctg"]),
        "timesteps": torch.arange(N_STEPS).expand(n, -1).contiguous(),
        "target_actions": f("actions", a["actions"]),
        "target_next_states": f("states", a["states"][:, 1:]),
        "mask": torch.ones(n, N_STEPS),
    }


def loss_data(data: str | None, batch: int, n_val: int, seed: int) -> tuple[Any, list[dict], str]:
    """(endless train-batch factory, fixed validation batches, description)."""
    if data:
        from ttompc.data.config import DataConfig
        from ttompc.data.datamodule import TrajectoryDataModule

        dm = TrajectoryDataModule(DataConfig(paths=[data], batch_size=batch, seed=seed))
        dm.setup("fit")
        val = [b for _, b in zip(range(max(n_val // batch, 1)), dm.val_dataloader(), strict=False)]
        return (lambda: iter(dm.train_dataloader())), val, f"dataset {data} (TrajectoryDataModule)"
    n_train = 1024
    arrays = generated_arrays(n_train + n_val, seed)
    train_a = {k: v[:n_train] for k, v in arrays.items()}
    stats = NormStats.from_arrays({**train_a, "states": train_a["states"][:, :-1]})
    train_t = tensors(train_a, stats)
    val_t = tensors({k: v[n_train:] for k, v in arrays.items()}, stats)
    val = [{k: v[i : i + batch] for k, v in val_t.items()} for i in range(0, n_val, batch)]

    def batches() -> Iterator[dict]:
        g = torch.Generator().manual_seed(seed)
        while True:
            for idx in torch.randperm(n_train, generator=g).split(batch):
                if len(idx) == batch:
                    yield {k: v[idx] for k, v in train_t.items()}

    desc = f"generated free-flyer trajectories ({n_train} train / {n_val} val, smooth random thrust, seed {seed})"
    return batches, val, desc


def val_loss(mod: TrajectoryTransformerModule, val: list[dict], mode: str) -> float:
    mod.eval()
    with torch.no_grad(), precision_ctx(mode):
        losses = [float(mod._losses(b)[0]) * len(b["states"]) for b in val]
    mod.train()
    return sum(losses) / sum(len(b["states"]) for b in val)


def loss_check(runs: list[tuple[str, int]], steps: int, every: int, batch: int, data: str | None) -> dict:
    """Validation loss every ``every`` steps of each (mode, init seed) run, on the same batch sequence."""
    torch.set_num_threads(2)
    batches, val, desc = loss_data(data, batch, n_val=128, seed=0)
    out: dict[str, Any] = {"data": desc, "steps": steps, "batch": batch, "size": "0.6M", "lr": 1e-3, "runs": {}}
    for mode, seed in runs:
        mod, opt = build("0.6M", seed=seed)
        torch.manual_seed(1000)  # same dropout masks' stream for every run
        curve, it = {}, batches()
        for step in range(1, steps + 1):
            train_step(mod, opt, next(it), mode)
            if step % every == 0:
                curve[step] = round(val_loss(mod, val, mode), 5)
        out["runs"][f"{mode}/init{seed}"] = curve
    torch.set_float32_matmul_precision("highest")
    return out


# ------------------------------------------------------------------------------------------------------- main
def default_cases(paper: bool, compile_: bool) -> list[Case]:
    """Full grid where it decides something (0.6M, the zoo size), fewer cases elsewhere: on a loaded 2-core machine
    each case costs minutes. Compilation takes minutes per case here, so only the 0.6M cases are compiled."""
    cases = [Case("tiny", m, 2, 32) for m in ("fp32", "bf16")]
    cases += [
        Case("0.6M", m, 2, 32) for m in ["fp32", "bf16", "bf16mm"] + (["compile", "compile-bf16"] if compile_ else [])
    ]
    cases += [Case("0.6M", m, 1, 32) for m in ("fp32", "bf16")]
    cases += [Case("0.6M", "bf16", 2, 64), Case("0.6M", "fp32", 2, 128), Case("0.6M", "bf16", 2, 128)]
    cases += [Case("1.8M", m, 2, 32) for m in ("fp32", "bf16", "bf16mm")]
    if paper:  # batch 8: a paper-size step at 32 takes too long on a shared 2-core machine
        cases += [Case("11M", m, t, 8) for t in (2, 1) for m in ("fp32", "bf16")]
    return cases + layout_cases()


def layout_cases() -> list[Case]:
    """Both layouts at equal width, depth, precision and batch, one thread (how the zoo trains: one run per core)."""
    return [
        Case(size, mode, 1, 32, layout=layout)
        for size in ("0.6M", "1.8M")
        for mode in ("fp32", "bf16")
        for layout in ("interleaved", "stacked")
    ]


def layout_rows(cases: list[Case]) -> list[dict[str, Any]]:
    """Stacked vs interleaved at equal (size, mode, threads, batch): trajectories per CPU-second and their ratio."""
    per_cpu = {c.name: c.batch / statistics.median(c.cpu_times) for c in cases}
    rows = []
    for c in cases:
        twin = Case(c.size, c.mode, c.threads, c.batch, layout="interleaved").name
        if c.layout == "stacked" and twin in per_cpu:
            rows.append(
                {
                    "size": c.size,
                    "mode": c.mode,
                    "threads": c.threads,
                    "batch": c.batch,
                    "interleaved_traj_per_cpu_s": round(per_cpu[twin], 2),
                    "stacked_traj_per_cpu_s": round(per_cpu[c.name], 2),
                    "stacked_over_interleaved": round(per_cpu[c.name] / per_cpu[twin], 2),
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=3, help="timing rounds (median)")
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--no-paper", action="store_true", help="skip the 11M size")
    ap.add_argument("--sizes", help="comma-separated subset of the sizes, e.g. 0.6M,11M (default: all)")
    ap.add_argument("--loss-mode", default="bf16", help="candidate precision for the loss check")
    ap.add_argument("--loss-steps", type=int, default=100, help="0: no loss check")
    ap.add_argument("--loss-every", type=int, default=25)
    ap.add_argument("--loss-batch", type=int, default=16)
    ap.add_argument("--data", help="dataset folder for the loss check (default: generated here)")
    ap.add_argument("--layout-study", action="store_true", help="only the interleaved-vs-stacked cases")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()

    machine = Machine()
    cases = layout_cases() if args.layout_study else default_cases(not args.no_paper, not args.no_compile)
    if args.sizes:
        cases = [c for c in cases if c.size in args.sizes.split(",")]
    t0 = time.perf_counter()
    speed(cases, args.reps)
    speed_s = time.perf_counter() - t0
    base: dict[str, Case] = {}
    for c in cases:  # the size's interleaved fp32 case with the most threads, then the smallest batch
        b = base.get(c.size)
        key = lambda x: (x.layout == "interleaved", x.mode == "fp32", x.threads == BASE[1], -x.batch)  # noqa: E731
        if b is None or key(c) > key(b):
            base[c.size] = c
    rows = []
    for c in cases:
        med, cpu = statistics.median(c.times), statistics.median(c.cpu_times)
        b = base[c.size]
        traj, base_traj = c.batch / med, b.batch / statistics.median(b.times)
        rows.append(
            {
                "size": c.size,
                "layout": c.layout,
                "mode": c.mode,
                "threads": c.threads,
                "batch": c.batch,
                "step_s": round(med, 4),
                "step_s_all": [round(t, 4) for t in c.times],
                "cpu_s": round(cpu, 4),
                "tokens_per_s": round(c.tokens / med, 1),
                "trajectories_per_cpu_s": round(c.batch / cpu, 2),
                # trajectories/s vs the size's baseline (interleaved fp32 eager, 2 threads unless not run)
                "speedup": round(traj / base_traj, 3),
                "speedup_cpu": round(c.batch / cpu / (b.batch / statistics.median(b.cpu_times)), 3),
                "compile_s": round(c.compile_s, 1) if c.compile_s is not None else None,
            }
        )
    load_mid = load_average()
    t1 = time.perf_counter()
    runs = [("fp32", 0), (args.loss_mode, 0), ("fp32", 1)]
    losses = loss_check(runs, args.loss_steps, args.loss_every, args.loss_batch, args.data) if args.loss_steps else None
    best = {size: max((r for r in rows if r["size"] == size), key=lambda r: r["speedup"]) for size in base}
    result = {
        "bench": "train_speed",
        "machine": {**machine.record(), "load_after_speed": load_mid},
        "tokens_per_trajectory": {k: N_STEPS * v for k, v in TOKENS_PER_STEP.items()},
        "reps": args.reps,
        "speed_s": round(speed_s, 1),
        "loss_s": round(time.perf_counter() - t1, 1),
        "cases": rows,
        "baseline_per_size": {k: b.name for k, b in base.items()},
        "fastest_per_size": {
            k: f"{r['layout']}/{r['mode']}/t{r['threads']}/b{r['batch']} x{r['speedup']}" for k, r in best.items()
        },
        "layouts": layout_rows(cases),
        "loss_check": losses,
    }
    write_result(result, args.out)


if __name__ == "__main__":
    main()
