"""The autoregressive rollout: cached == full recompute, restarts from a context, MPC cache reuse, conditioning."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from ttompc.policy import ModelConfig, Planner, TrajectoryGPT
from ttompc.policy.rollout import RolloutContext, rollout
from ttompc.policy.stats import NormStats

B, STEPS = 3, 12
ZOO = Path(__file__).resolve().parents[1] / "zoo" / "models"


@pytest.fixture(params=["interleaved", "stacked"])
def layout(request: pytest.FixtureRequest) -> str:
    return str(request.param)


def _model(dtype: torch.dtype, layout: str = "interleaved") -> TrajectoryGPT:
    torch.manual_seed(0)
    cfg = ModelConfig(n_embd=32, n_layer=2, n_head=4, max_steps=STEPS, layout=layout)  # type: ignore[arg-type]
    return TrajectoryGPT(cfg).to(dtype)  # left in train mode on purpose: rollouts must switch dropout off


def _start(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(3)
    s0 = torch.randn(B, 6, generator=g, dtype=dtype)
    goal = torch.randn(B, 6, generator=g, dtype=dtype)
    return s0, goal, torch.tensor([-1.0, -2.0, -3.0], dtype=dtype)


@pytest.mark.parametrize(("dtype", "atol"), [(torch.float32, 1e-5), (torch.float64, 1e-10)])
def test_cached_equals_full_recompute(toy, toy_stats: NormStats, dtype: torch.dtype, atol: float, layout: str) -> None:
    model, (s0, goal, rtg0) = _model(dtype, layout), _start(dtype)
    dyn = toy.batched_model([])
    fast = rollout(model, toy_stats, dyn, "l1", s0, goal, rtg0, 0.0, use_cache=True)
    slow = rollout(model, toy_stats, dyn, "l1", s0, goal, rtg0, 0.0, use_cache=False)
    assert fast.states.shape == (B, STEPS + 1, 6) and fast.actions.shape == (B, STEPS, 3)
    assert fast.rtg.shape == (B, STEPS + 1) and fast.ctg.shape == (B, STEPS + 1)
    for name in ("states", "actions", "rtg", "ctg"):
        torch.testing.assert_close(getattr(fast, name), getattr(slow, name), rtol=0, atol=atol)
    assert model.training  # restored


def test_conditioning_updates(toy, toy_stats: NormStats) -> None:
    model, (s0, goal, rtg0) = _model(torch.float64), _start(torch.float64)
    dyn = toy.batched_model([])
    s0[0, :3] = 0.0  # inside the toy keep-out ball
    res = rollout(model, toy_stats, dyn, "l1", s0, goal, rtg0, 2.0)
    torch.testing.assert_close(res.rtg[:, 1:] - res.rtg[:, :-1], res.actions.abs().sum(-1))  # rtg += c(a)
    torch.testing.assert_close(
        res.states[:, 1:],
        dyn.step(res.states[:, :-1].reshape(-1, 6), res.actions.reshape(-1, 3), 0).reshape(B, STEPS, 6),
    )
    assert torch.all(res.ctg == 2.0)  # a plan holds its ctg
    # the executed history counts violations: ctg_{t+1} = ctg_t − violations(s_{t+1})
    ctx = RolloutContext.start(model, toy_stats, dyn, "l1", s0, goal, rtg0, 2.0)
    ctx.advance(res.actions[:, 0], s0)  # back inside the keep-out ball
    torch.testing.assert_close(ctx.ctg[:, -1], 2.0 - dyn.violations(s0, 1))
    assert bool(dyn.violations(s0, 1)[0] > 0)


@pytest.mark.parametrize("use_cache", [True, False])
def test_restart_from_context_equals_slice(toy, toy_stats: NormStats, use_cache: bool, layout: str) -> None:
    model, (s0, goal, rtg0) = _model(torch.float64, layout), _start(torch.float64)
    dyn = toy.batched_model([])
    full = rollout(model, toy_stats, dyn, "l1", s0, goal, rtg0, 0.0)
    t0 = 5
    ctx = RolloutContext(
        model,
        toy_stats,
        dyn,
        "l1",
        full.states[:, : t0 + 1],
        goal[:, None].expand(-1, t0 + 1, -1),
        full.rtg[:, : t0 + 1],
        full.ctg[:, : t0 + 1],
        full.actions[:, :t0],
        use_cache=use_cache,
    )
    part = ctx.rollout(STEPS - t0)
    assert part.start == t0
    for name in ("states", "actions", "rtg", "ctg"):
        torch.testing.assert_close(getattr(part, name), getattr(full, name)[:, t0:], rtol=0, atol=1e-10)


def test_mpc_context_reuses_cache_correctly(toy, toy_stats: NormStats, layout: str) -> None:
    """advance() + rollout() on the cached context equals a from-scratch recompute of the same history."""
    model, (s0, goal, rtg0) = _model(torch.float64, layout), _start(torch.float64)
    # the deciding tokens of steps 0..t: interleaved g R C s, then a g R C s per step; stacked one per step
    cached_tokens = {"interleaved": lambda steps: 5 * steps - 1, "stacked": lambda steps: steps}[layout]
    dyn = toy.batched_model([])
    ctx = RolloutContext.start(model, toy_stats, dyn, "l1", s0, goal, rtg0, 1.0)
    g = torch.Generator().manual_seed(7)
    for t in range(4):
        plan = ctx.rollout(min(4, STEPS - t))
        executed = plan.actions[:, 0] + 0.01 * torch.randn(B, 3, generator=g, dtype=torch.float64)
        measured = dyn.step(ctx.states[:, -1], executed, t) + 0.01 * torch.randn(B, 6, generator=g, dtype=torch.float64)
        ctx.advance(executed, measured)
        assert ctx.t == t + 1 and ctx._cache is not None and ctx._cache.length == cached_tokens(t + 1)
    fresh = RolloutContext(
        model, toy_stats, dyn, "l1", ctx.states, ctx.goals, ctx.rtg, ctx.ctg, ctx.actions, use_cache=False
    )
    a, b = ctx.rollout(6), fresh.rollout(6)
    torch.testing.assert_close(a.states, b.states, rtol=0, atol=1e-10)
    torch.testing.assert_close(a.actions, b.actions, rtol=0, atol=1e-10)
    # The MPC context subtracts measured violations from ctg (reference behaviour) and adds c(a) to rtg.
    torch.testing.assert_close(ctx.rtg[:, 1:] - ctx.rtg[:, :-1], ctx.actions.abs().sum(-1))


@pytest.mark.parametrize("name", ["quadrotor-ft-tto-v6", "quadrotor-tto-small"])  # stacked, interleaved
def test_shipped_model_mpc_window_equals_full_recompute(name: str) -> None:
    """What TTO-MPC runs, on shipped float32 weights: 4 episodes advanced 20 steps, then a 10-step window from the
    cached history (folded normalisation, ``Decoder``) equals the reference's full recompute within float32
    rounding, leaves the cached history as it was and returns ordinary tensors (not ``inference_mode`` ones)."""
    planner = Planner.from_pretrained(ZOO / name)
    problems = [planner.scenario.sample(np.random.default_rng(seed)) for seed in range(4)]
    ctx = planner.context(problems, rtg0=float(planner.stats.mean["rtg"][0]))
    for _ in range(20):
        plan = ctx.rollout(1)
        ctx.advance(plan.actions[:, 0], plan.states[:, 1])
    assert ctx._cache is not None
    history = ctx._cache.length
    executed = (ctx.states, ctx.goals, ctx.rtg, ctx.ctg, ctx.actions)
    fresh = RolloutContext(planner.model, planner.stats, ctx.dynamics, ctx.cost_norm, *executed, use_cache=False)
    fast, slow = ctx.rollout(10), fresh.rollout(10)
    assert fast.states.dtype == torch.float32 and fast.start == slow.start == 20
    assert not any(getattr(fast, part).is_inference() for part in ("states", "actions", "rtg", "ctg"))
    assert ctx._cache.length == history
    for part in ("states", "actions", "rtg", "ctg"):
        a, b = getattr(fast, part), getattr(slow, part)
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * float(b.abs().max()), msg=part)


def test_rejects_horizon_beyond_model(toy, toy_stats: NormStats) -> None:
    model, (s0, goal, rtg0) = _model(torch.float32), _start(torch.float32)
    with pytest.raises(ValueError, match="outside"):
        rollout(model, toy_stats, toy.batched_model([]), "l1", s0, goal, rtg0, horizon=STEPS + 1)


def test_rollout_matches_the_teacher_forced_forward_pass(toy, toy_stats: NormStats, layout: str) -> None:
    """Feeding the generated trajectory back through ``forward`` (the training path, normalised with NumPy) predicts
    exactly the actions the rollout took: both paths see the same tokens, order and normalisation."""
    model, (s0, goal, rtg0) = _model(torch.float64, layout), _start(torch.float64)
    res = rollout(model, toy_stats, toy.batched_model([]), "l1", s0, goal, rtg0, 1.0)
    L = STEPS

    def norm(key: str, x: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(toy_stats.normalize(key, x.numpy()))

    model.eval()
    a_pred, _ = model(
        norm("goals", goal[:, None].expand(-1, L, -1)),
        norm("rtg", res.rtg[:, :L, None]),
        norm("ctg", res.ctg[:, :L, None]),
        norm("states", res.states[:, :L]),
        norm("actions", res.actions),
        torch.arange(L).expand(B, -1),
    )
    torch.testing.assert_close(a_pred, norm("actions", res.actions), rtol=0, atol=1e-10)


def test_norm_stats_round_trip_in_the_callers_dtype(toy_stats: NormStats) -> None:
    x = torch.randn(4, 6, dtype=torch.float64)
    for dtype in (torch.float64, torch.float32, torch.float64):  # the tensor cache is per dtype
        y = toy_stats.normalize("states", x.to(dtype))
        assert y.dtype == dtype
        torch.testing.assert_close(y.double(), torch.as_tensor(toy_stats.normalize("states", x.numpy())), **_tol(dtype))
        torch.testing.assert_close(toy_stats.denormalize("states", y), x.to(dtype), **_tol(dtype))
    assert not torch.allclose(toy_stats.normalize("states", x), x)  # the statistics are not the identity
    with pytest.raises(ValueError, match="missing"):
        NormStats.from_dict({"mean": toy_stats.to_dict()["mean"]})


def _tol(dtype: torch.dtype) -> dict[str, float]:
    return {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 0.0, "atol": 1e-12}
