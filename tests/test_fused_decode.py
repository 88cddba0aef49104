"""The fused decode (``decoder="fused"``, ``ttompc.policy.fused``): equal to the torch cached rollout on the three
built-in scenarios, the torch KV cache left as it was, the refusals and fallbacks, and an MPC run with it."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
import torch

from ttompc.mpc.loop import EpisodeStart, MPCRun, run_mpc_batch
from ttompc.mpc.methods import MethodInputs, model_method
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.tto import RolloutGroup
from ttompc.policy import ModelConfig, Planner, RolloutContext, TrajectoryGPT
from ttompc.policy.fused import FusedDecoder
from ttompc.policy.rollout import stage_cost_torch
from ttompc.policy.stats import NormStats
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Problem
from ttompc.solvers.scp import solve_rel

RTOL = 1e-4


@pytest.fixture(autouse=True)
def _one_torch_thread() -> Iterator[None]:
    from ttompc.parallel import single_torch_thread

    with single_torch_thread():
        yield


def planner(scenario: str, activation: str = "relu", layout: str = "stacked", seed: int = 0) -> Planner:
    """A random 2-layer stacked model with statistics of the scenario's magnitudes (so that the generated plans move
    the state: a test that compares plans must compare plans that differ from step to step)."""
    sc = get_scenario(scenario)
    torch.manual_seed(seed)
    dims = {"state_dim": sc.state_dim, "control_dim": sc.control_dim, "max_steps": sc.n_steps}
    cfg = ModelConfig(n_embd=32, n_layer=2, n_head=4, dropout=0.0, layout=layout,
                      activation=activation, **dims)  # type: ignore[arg-type]  # fmt: skip
    rng = np.random.default_rng(seed)
    m = sc.control_dim
    problems = [sc.sample(rng) for _ in range(4)]
    S = np.stack([sc.to_model_states(p, p.x0[None])[0] for p in problems])
    s_sd = S.std(axis=0) + 1e-3
    a_sd = np.asarray(sc.control_scale or np.ones(m))
    stats = NormStats(
        mean={"states": S.mean(axis=0), "actions": 0.3 * a_sd, "goals": S.mean(axis=0), "rtg": [-0.5], "ctg": [1.0]},
        std={"states": s_sd, "actions": a_sd, "goals": s_sd, "rtg": [0.3], "ctg": [2.0]},
    )
    return Planner(TrajectoryGPT(cfg), sc, stats)


def problems(scenario: str, count: int = 3) -> list[Problem]:
    sc = get_scenario(scenario)
    return [sc.sample(np.random.default_rng(10 + k)) for k in range(count)]


def assert_close(a: torch.Tensor, b: torch.Tensor, what: str) -> None:
    """Equal up to RTOL relative to each row's magnitude (float32 rounding, amplified over the generated steps)."""
    scale = b.abs().amax(dim=tuple(range(1, b.ndim)), keepdim=True).clamp_min(1e-6)
    err = float(((a - b).abs() / scale).max())
    assert err < RTOL, f"{what}: relative error {err:.2e}"


@pytest.mark.parametrize("scenario", ["freeflyer", "quadrotor", "rpod"])
@pytest.mark.parametrize("activation", ["relu", "gelu"])
def test_fused_equals_torch_and_leaves_the_cache(scenario: str, activation: str) -> None:
    """From step 0 and after several advances: the fused rollout's states, actions and rtg equal the torch cached
    rollout's, the plans move, and the cache's length and history are what the torch path leaves."""
    pl, probs = planner(scenario, activation), problems(scenario)
    torch_ctx = pl.context(probs, rtg0=[-0.5, -1.0, -2.0])
    fused_ctx = pl.context(probs, rtg0=[-0.5, -1.0, -2.0], decoder="fused")
    assert fused_ctx.decoder == "fused" and fused_ctx.fallback is None
    H = 8
    for t in range(5):
        ref, res = torch_ctx.rollout(H), fused_ctx.rollout(H)
        assert res.start == ref.start == t and res.states.dtype == torch.float32
        for name in ("states", "actions", "rtg"):
            assert getattr(res, name).shape == getattr(ref, name).shape
            assert_close(getattr(res, name), getattr(ref, name), f"{scenario} {activation} t={t} {name}")
        torch.testing.assert_close(res.ctg, ref.ctg)
        # rtg_{k+1} − rtg_k = c(a_k), up to the float32 rounding of rtg (the increments are far below its magnitude)
        eps = 4 * torch.finfo(torch.float32).eps * float(res.rtg.abs().max())
        cost = stage_cost_torch(res.actions, pl.scenario.cost_norm)
        assert float(cost.min()) > 20 * eps  # so that a cost 10% off shows
        torch.testing.assert_close(res.rtg[:, 1:] - res.rtg[:, :-1], cost, rtol=1e-3, atol=eps)
        assert float((ref.states[:, 1:] - ref.states[:, :-1]).abs().max()) > 1e-6  # the plan moves
        cache = fused_ctx._cache
        assert cache is not None and cache.length == torch_ctx._cache.length == t  # type: ignore[union-attr]
        before = cache.k[:, :, :, :t].clone(), cache.v[:, :, :, :t].clone()
        fused_ctx.rollout(H)
        assert cache.length == t  # a rollout leaves the history's length ...
        assert torch.equal(cache.k[:, :, :, :t], before[0]) and torch.equal(
            cache.v[:, :, :, :t], before[1]
        )  # ... and it
        # executed along the torch plan: both caches then hold the same history
        for ctx in (torch_ctx, fused_ctx):
            ctx.advance(ref.actions[:, 0], ref.states[:, 1])
        hist = torch_ctx._cache.k[:, :, :, : t + 1]  # type: ignore[union-attr]
        assert_close(cache.k[:, :, :, : t + 1], hist, "cache keys")


def test_deferred_extension_and_weight_updates() -> None:
    """The fused extension of several deferred steps in one pass equals the torch one, and a context built after an
    in-place weight update (an optimizer step, ``load_state_dict``) computes with the new weights."""
    pl, probs = planner("quadrotor"), problems("quadrotor", 2)
    ctxs = [pl.context(probs, rtg0=-1.0, decoder=d) for d in ("torch", "fused")]
    plan = ctxs[0].rollout(4)
    for ctx in ctxs:
        ctx.defer_cache = True
        for k in range(4):
            ctx.advance(plan.actions[:, k], plan.states[:, k + 1])
    assert_close(ctxs[1].rollout(5).actions, ctxs[0].rollout(5).actions, "after a deferred extension")
    before = ctxs[1].rollout(5).actions
    with torch.no_grad():
        for p in pl.model.blocks[0].parameters():
            p.mul_(1.5)
    ctxs = [pl.context(probs, rtg0=-1.0, decoder=d) for d in ("torch", "fused")]
    after = ctxs[1].rollout(5).actions
    assert_close(after, ctxs[0].rollout(5).actions, "after a weight update")
    assert float((after - before).abs().max()) > 1e-3 * float(before.abs().max())  # the update changed the plan


def test_an_advance_claims_the_rollouts_first_token() -> None:
    """The advance by the executed step t takes the token of step t that the rollout from step t wrote into the
    history (no compute) where the step's inputs are the rollout's, and computes it where they are not (an rtg fed
    after the rollout) or where no rollout ran at the step: in every case the history and the next rollouts equal
    the torch path's."""
    pl, probs = planner("quadrotor"), problems("quadrotor", 2)
    torch_ctx, fused_ctx = (pl.context(probs, rtg0=-1.0, decoder=d) for d in ("torch", "fused"))
    for t in range(6):
        ref = torch_ctx.rollout(5)
        if t != 3:  # step 3: no rollout
            assert_close(fused_ctx.rollout(5).actions, ref.actions, f"t={t} actions")
        if t == 4:  # a value fed after the rollout: the rollout's token of step 4 is not the history's
            for ctx in (torch_ctx, fused_ctx):
                ctx.rtg[:, -1] = -0.7
        for ctx in (torch_ctx, fused_ctx):
            ctx.advance(ref.actions[:, 0], ref.states[:, 1])
        cache, want = fused_ctx._cache, torch_ctx._cache
        assert cache is not None and want is not None and cache.length == want.length == t + 1
        assert_close(cache.k[:, :, :, : t + 1], want.k[:, :, :, : t + 1], f"t={t} keys")
        assert_close(cache.v[:, :, :, : t + 1], want.v[:, :, :, : t + 1], f"t={t} values")
    decoder = fused_ctx._decoder
    assert isinstance(decoder, FusedDecoder) and decoder.claimed == 4  # steps 0, 1, 2 and 5
    assert_close(fused_ctx.rollout(5).states, torch_ctx.rollout(5).states, "after the claims")


def test_refusals_and_fallbacks() -> None:
    """``fused`` refuses what it cannot run, naming why; ``auto`` runs the torch path there with the reason kept."""
    probs = problems("freeflyer", 1)
    interleaved = planner("freeflyer", layout="interleaved")
    with pytest.raises(ValueError, match="stacked layout"):
        interleaved.context(probs, rtg0=-1.0, decoder="fused")
    with pytest.raises(ValueError, match="stacked layout"):
        RolloutGroup(interleaved, decoder="fused")
    with pytest.warns(RuntimeWarning, match="stacked layout"):
        ctx = interleaved.context(probs, rtg0=-1.0, decoder="auto")
    assert ctx.decoder == "torch" and ctx.fallback is not None and "interleaved" in ctx.fallback
    stacked = planner("freeflyer")
    with pytest.raises(ValueError, match="use_cache"):
        stacked.context(probs, rtg0=-1.0, use_cache=False, decoder="fused")
    with pytest.raises(ValueError, match="float32"):
        RolloutContext.start(stacked.model.double(), stacked.stats, stacked.scenario.batched_model(probs), "l1",
                             torch.zeros(1, 6), torch.zeros(1, 6), -1.0, decoder="fused")  # fmt: skip
    stacked.model.float()
    dyn = stacked.scenario.batched_model(probs)
    bare = type("Bare", (), {"step": dyn.step, "violations": dyn.violations})()  # a BatchedModel without fused_step
    with pytest.raises(ValueError, match="no fused_step"):
        RolloutContext.start(stacked.model, stacked.stats, bare, "l1", torch.zeros(1, 6), torch.zeros(1, 6), -1.0,
                             decoder="fused")  # fmt: skip
    assert RolloutContext.start(stacked.model, stacked.stats, dyn, "l1", torch.zeros(1, 6), torch.zeros(1, 6), -1.0,
                                decoder="auto").decoder == "fused"  # fmt: skip
    with pytest.raises(ValueError, match="decoder must be one of"):
        MPCSettings(decoder="numba")


def test_mpc_with_the_fused_decoder() -> None:
    """Two quadrotor episodes in lockstep, 4 MPC steps: ``mpc.decoder=fused`` executes the controls of ``torch`` (the
    quadrotor's strictly convex stage cost keeps each window's optimum a continuous function of its warm start; the
    free-flyer's l1 optimum is not unique, and float rounding of a warm start may pick another)."""
    sc, pl = get_scenario("quadrotor"), planner("quadrotor")
    probs = problems("quadrotor", 2)
    starts = [EpisodeStart(p, solve_rel(sc, p).cost, 3) for p in probs]

    def episodes(decoder: str) -> list:
        settings = MPCSettings(decoder=decoder)
        provs = model_method("TTO").providers(MethodInputs(settings, [None, None], pl))
        out = run_mpc_batch(sc, starts, provs, MPCRun(5, settings, max_steps=4))
        assert provs[0].context is not None and provs[0].context.decoder == decoder  # type: ignore[attr-defined]
        return out

    ref, fused = episodes("torch"), episodes("fused")
    for a, b in zip(ref, fused, strict=True):
        assert a.U.shape == b.U.shape and np.abs(a.U).max() > 0
        np.testing.assert_allclose(b.U, a.U, rtol=1e-4, atol=1e-4 * np.abs(a.U).max())
        np.testing.assert_allclose(b.X, a.X, rtol=1e-4, atol=1e-6)


def test_the_worked_example_gets_the_fused_decoder() -> None:
    """A user's scenario with its dynamics written once (examples/di2d.py, a ``CompiledScenario``) runs the fused
    decode, and it plans what the torch decode plans."""
    from pathlib import Path

    spec = f"{Path(__file__).resolve().parents[1] / 'examples' / 'di2d.py'}:DoubleIntegrator2D"
    pl, probs = planner(spec), problems(spec, 2)
    torch_ctx, fused_ctx = (pl.context(probs, rtg0=-1.0, decoder=d) for d in ("torch", "fused"))
    assert fused_ctx.decoder == "fused"
    for _ in range(3):
        ref, res = torch_ctx.rollout(6), fused_ctx.rollout(6)
        for name in ("states", "actions", "rtg"):
            assert_close(getattr(res, name), getattr(ref, name), f"di2d {name}")
        assert float((ref.states[:, 1:] - ref.states[:, :-1]).abs().max()) > 1e-6  # the plan moves
        for ctx in (torch_ctx, fused_ctx):
            ctx.advance(ref.actions[:, 0], ref.states[:, 1])
