"""``MPCSettings.decode_every``: TTO-MPC decodes a plan every k steps and serves the windows in between from slices
of it (``ttompc.mpc.tto.RolloutGroup``), on the short free-flyer with a tiny random planner."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import asdict

import mpc_fakes
import numpy as np
import pytest
import torch

from ttompc.cli import main
from ttompc.config import ConfigError
from ttompc.mpc.departures import departures
from ttompc.mpc.loop import EpisodeStart, MPCRun, run_mpc_batch
from ttompc.mpc.methods import MethodInputs, model_method
from ttompc.mpc.settings import MPCSettings, protocol_settings
from ttompc.mpc.tto import RolloutGroup, TTOProvider
from ttompc.policy.rollout import RolloutContext
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.scp import solve_rel


@pytest.fixture(autouse=True)
def _one_torch_thread() -> Iterator[None]:
    from ttompc.parallel import single_torch_thread

    with single_torch_thread():
        yield


@pytest.fixture(scope="module")
def setup() -> tuple[Scenario, list[Problem], list[float]]:
    sc = get_scenario(mpc_fakes.FreeFlyerShort.name)
    problems = [sc.sample(np.random.default_rng(k)) for k in (1, 2)]
    return sc, problems, [solve_rel(sc, p).cost for p in problems]


class Decodes:
    """Spy on ``RolloutContext.rollout``: the step, length and result of every decode."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.calls: list[tuple[int, int, np.ndarray, np.ndarray]] = []
        rollout = RolloutContext.rollout

        def spy(ctx: RolloutContext, horizon: int) -> object:
            res = rollout(ctx, horizon)
            self.calls.append((ctx.t, horizon, res.states.double().numpy(), res.actions.double().numpy()))
            return res

        monkeypatch.setattr(RolloutContext, "rollout", spy)

    def steps(self) -> list[tuple[int, int]]:
        return [(t, h) for t, h, _, _ in self.calls]


def drive(sc: Scenario, problems: list[Problem], costs: list[float], k: int, lengths: list[int]) -> list[list]:
    """Two grouped TTO providers (``decode_every`` = k) over len(``lengths``) steps without the SCP: at step t each
    asks the window of ``lengths[t]`` steps (cut at N) and executes its warm start's first control. -> each member's
    (measured state, warm start) per step."""
    planner = mpc_fakes.tiny_planner()
    group = RolloutGroup(planner, decode_every=k)
    provs = [TTOProvider(planner, group=group) for _ in problems]
    for prov, p, c in zip(provs, problems, costs, strict=True):
        prov.reset(sc, p, c)
    N = problems[0].n_steps
    xs, out = [p.x0 for p in problems], [[] for _ in provs]
    for t, L in enumerate(lengths):
        w = Window(t, min(L, N - t), N)
        for b, (prov, p) in enumerate(zip(provs, problems, strict=True)):
            ws = prov.warm_start(w, xs[b])
            out[b].append((xs[b], ws))
            xs[b] = sc.step(p, t, xs[b], ws.U[0])
            prov.observe(ws.U[0], xs[b], ws.X, ws.U)
    assert group.t == len(lengths)  # the context advanced with every executed step
    return out


def test_decode_every_1_is_the_paper_loop(setup: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """k = 1 (explicit, as a protocol override) runs the episodes of the default settings bitwise: one decode of H
    steps at every step."""
    sc, problems, costs = setup
    planner = mpc_fakes.tiny_planner()
    decodes = Decodes(monkeypatch)
    starts = [EpisodeStart(p, c, 3) for p, c in zip(problems, costs, strict=True)]

    def episodes(settings: MPCSettings) -> list:
        provs = model_method("TTO").providers(MethodInputs(settings, [None, None], planner))
        return run_mpc_batch(sc, starts, provs, MPCRun(5, settings, max_steps=4))

    default = episodes(MPCSettings())
    assert decodes.steps() == [(t, 5) for t in range(4)]
    explicit = episodes(protocol_settings("paper", {"decode_every": 1}))
    for a, b in zip(default, explicit, strict=True):
        np.testing.assert_array_equal(a.X, b.X)
        np.testing.assert_array_equal(a.U, b.U)


def test_windows_between_decodes_are_slices_of_the_last(setup: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """k = 3, H = 5: a decode of H + 2 steps at t = 0, 3, 6 (conditioning there only); the windows between are its
    slices from t − t_decode (X[0] the measured state), their targets the slices' last states, and they are charged
    none of the model's time."""
    sc, problems, costs = setup
    decodes = Decodes(monkeypatch)
    conditioned: list[int] = []
    conditioning = TTOProvider.conditioning
    monkeypatch.setattr(TTOProvider, "conditioning", lambda self, t: conditioned.append(t) or conditioning(self, t))
    charges: list[tuple[float, float]] = []
    rollout = RolloutGroup.rollout

    def group_rollout(group: RolloutGroup, slot: int, window: Window) -> tuple:
        res = rollout(group, slot, window)
        charges.append(res[2:])
        return res

    monkeypatch.setattr(RolloutGroup, "rollout", group_rollout)
    out = drive(sc, problems, costs, 3, [5] * 7)
    assert decodes.steps() == [(0, 7), (3, 7), (6, 7)]
    assert conditioned == [0, 0, 3, 3, 6, 6]
    for b, (p, steps) in enumerate(zip(problems, out, strict=True)):
        for t, (x, ws) in enumerate(steps):
            t_dec, _, S, A = decodes.calls[t // 3]
            j = t - t_dec
            X = sc.from_model_states(p, S[b, j : j + 6], start=t)
            X[0] = x
            np.testing.assert_array_equal(ws.X, X)
            np.testing.assert_array_equal(ws.U, A[b, j : j + 5])
            assert ws.terminal is not None
            np.testing.assert_array_equal(ws.terminal.target, ws.X[-1])
            share, shared = charges[2 * t + b]
            assert (share > 0) == (j == 0) and (shared > 0) == (j == 0 and b == 0)


def test_a_window_past_the_decode_decodes_again(setup: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """A window longer than what remains of the last decode decodes at its step (and restarts the count of k); an
    ``expect``ed window lengthens the decode; no decode runs past N."""
    sc, problems, costs = setup
    decodes = Decodes(monkeypatch)
    drive(sc, problems, costs, 3, [5, 7, 5, 5, 5])  # t = 1: 7 > 7 − 1 steps left
    assert decodes.steps() == [(0, 7), (1, 9), (4, 7)]
    decodes.calls.clear()
    N = problems[0].n_steps
    drive(sc, problems, costs, 3, [5] * N)  # the windows cut at N, the decodes too
    assert decodes.steps() == [(t, min(7, N - t)) for t in range(0, N, 3)]
    planner = mpc_fakes.tiny_planner()
    group = RolloutGroup(planner, decode_every=3)
    prov = TTOProvider(planner, group=group)
    prov.reset(sc, problems[0], costs[0])
    group.expect(0, 8)
    prov.warm_start(Window(0, 5, N), problems[0].x0)
    assert decodes.steps()[-1] == (0, 10)


def test_deferred_advances_extend_the_cache_in_one_pass(setup: tuple) -> None:
    """Between decodes the context advances without its KV cache (``defer_cache``, set by a group with k > 1); the
    next rollout extends it over the deferred steps in one pass: the rollout of per-step advances up to float
    rounding."""
    sc, problems, costs = setup
    planner = mpc_fakes.tiny_planner()
    ctxs = [planner.context(problems, rtg0=[-0.3, -0.4]) for _ in range(2)]
    ctxs[1].defer_cache = True
    for ctx in ctxs:
        ctx.rollout(5)  # the cache is built
    gen = torch.Generator().manual_seed(0)
    for _ in range(3):
        u = 1e-3 * torch.randn(2, sc.control_dim, generator=gen, dtype=torch.float64)
        s = ctxs[0].states[:, -1] + 1e-2 * torch.randn(2, sc.state_dim, generator=gen, dtype=torch.float64)
        for ctx in ctxs:
            ctx.advance(u, s)
    now, deferred = (ctx.rollout(5) for ctx in ctxs)
    torch.testing.assert_close(deferred.actions, now.actions, rtol=1e-5, atol=1e-9)
    torch.testing.assert_close(deferred.states, now.states, rtol=1e-5, atol=1e-9)
    for k in (1, 3):
        group = RolloutGroup(planner, decode_every=k)
        TTOProvider(planner, group=group).reset(sc, problems[0], costs[0])
        assert group.context is not None and group.context.defer_cache == (k > 1)


def test_decode_every_settings(setup: tuple, capsys: pytest.CaptureFixture[str]) -> None:
    """Validated >= 1, a departure from the paper for k > 1, an ``mpc.`` override of the commands, refused by
    DAgger's rollouts (their learners ask windows of their own H and would share one decode schedule)."""
    from ttompc.finetune.config import check_rollout_settings

    sc = setup[0]
    with pytest.raises(ConfigError, match="invalid decode_every=0: must be >= 1"):
        MPCSettings(decode_every=0)
    with pytest.raises(ConfigError, match="invalid decode_every=0: must be >= 1"):
        protocol_settings("paper", {"decode_every": 0})
    with pytest.raises(ValueError, match="decode_every must be >= 1"):
        RolloutGroup(mpc_fakes.tiny_planner(), decode_every=0)
    assert departures(MPCSettings(), sc) == departures(MPCSettings(decode_every=1), sc)
    (note,) = set(departures(MPCSettings(decode_every=3), sc)) - set(departures(MPCSettings(), sc))
    assert "decode every 3 steps" in note and "the paper decodes at every step" in note
    assert main(["evaluate", "mpc", "mpc.decode_every=2", "--print-config"]) == 0
    assert json.loads(capsys.readouterr().out)["settings"] == asdict(MPCSettings(decode_every=2))
    assert main(["evaluate", "mpc", f"scenario={sc.name}", "mpc.decode_every=0"]) == 2
    check_rollout_settings(MPCSettings(decode_every=1))
    with pytest.raises(ConfigError, match="decode_every=2") as err:
        check_rollout_settings(MPCSettings(decode_every=2))
    assert "dagger.eval.mpc.decode_every=1" in str(err.value)
