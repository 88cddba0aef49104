"""TTO-MPC's provider (paper §IV-C, Eq. (8)) and the batching of its rollouts.

``TTOProvider`` (TTO-MPC / FT-TTO-MPC): an H-step transformer rollout from the running ``RolloutContext``
(conditioned on rtg_0 = −κ·J_REL, ctg_0 = 0); the context is advanced with every executed action and measured
state, so its KV cache is extended, never recomputed. x̄ = the predicted state at t+H, through the provider's
terminal term (``ttompc.mpc.terminal``). The reward-to-go fed at each decode is its rtg mode's (``ttompc.mpc.rtg``).
A decode runs at every step (the paper's), or every k steps under ``MPCSettings.decode_every`` = k, the windows in
between sliced from it (``RolloutGroup``).
The TTO providers of B episodes run in lockstep (``run_mpc_batch``) share one batched context (``RolloutGroup``).
A method's providers under ``MPCSettings`` are made by its entry in ``ttompc.mpc.methods``.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from ttompc.mpc.providers import WarmStart
from ttompc.mpc.rtg import RTGFeed, rtg_feed
from ttompc.mpc.settings import Role
from ttompc.mpc.terminal import TargetFilter, TerminalTerm
from ttompc.scenarios.base import Problem, Scenario, Window

if TYPE_CHECKING:
    from ttompc.policy import Planner, RolloutContext

RTG_SIGMAS = 3.0  # the training range's lower end: mean − 3 std of the model's rtg statistics
RTG_FLOOR = 0.05  # ... and its upper end: −RTG_FLOOR·|rtg_0|, a budget of at least that fraction of rtg_0 left


def check_rtg_scale(value: float, key: str = "rtg_scale") -> None:
    """The conditioning scale κ of rtg_0 = −κ·J_REL must be positive: rewards-to-go are negative costs, so κ <= 0
    asks the model for a trajectory that costs nothing or less; raises ``ValueError`` naming ``key``."""
    if not value > 0:
        raise ValueError(
            f"{key} must be > 0, got {value}: the model is conditioned on rtg_0 = -{key}*J_REL, the reward-to-go "
            f"(minus the cost) of a trajectory costing {key} times REL's; 1 is the paper's, a model's own is in its "
            "bundle"
        )


class TTOProvider:
    """TTO-MPC: H-step rollout from a persistent rollout context (one per episode, KV cache reused; or one batched
    context shared by the providers of a ``group``), conditioned on rtg_0 = −``rtg_scale``·J_REL (None: the model's
    own, ``Planner.rtg_scale``; the paper: 1) and ctg_0 = 0; the target comes from ``terminal`` (None: the paper's
    target).

    ``rtg_mode`` names the reward-to-go fed at each step (``ttompc.mpc.rtg.RTG_MODES``; ``running``, the paper's, by
    default): the provider runs the mode its model can (``rtg_feed``: a model without a value output runs the
    ledger under ``value``), ``rtg_mode`` holds that one. ``plan`` is the episode's open-loop optimum for a mode that
    reads it (``oracle``; None: solved at ``reset``); ``backend`` solves the mode's own problems. Every mode but
    ``running`` is clipped to [μ − 3σ, −``RTG_FLOOR``·|rtg_0|] (μ, σ: the model's rtg statistics), the range training
    rows' rtg lie in.

    Inside a window the rollout still adds the model's own planned costs to the fed value (the rollout's rule).
    ``use_cache`` configures the provider's own group; a given ``group`` has its own."""

    role: Role = "learned"

    def __init__(
        self,
        planner: Planner,
        name: str = "",
        *,
        use_cache: bool = True,
        rtg_scale: float | None = None,
        terminal: TerminalTerm | None = None,
        rtg_mode: str = "running",
        group: RolloutGroup | None = None,
        backend: str = "auto",
        plan: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        mode = rtg_feed(rtg_mode, planner)
        self.planner, self.name = planner, name or type(self).__name__
        self.rtg_scale = planner.rtg_scale if rtg_scale is None else rtg_scale
        check_rtg_scale(self.rtg_scale)
        self.rtg_mode = mode.name
        self.rtg = mode(backend, plan)
        self.target = terminal if terminal is not None else TargetFilter()
        self.group = group or RolloutGroup(planner, use_cache=use_cache)
        if self.group.planner is not planner:
            raise ValueError("the providers of a RolloutGroup must share its planner")
        self.slot = self.group.add(self)

    @property
    def context(self) -> RolloutContext | None:
        """The rollout context of this provider's group (row ``slot`` is this episode)."""
        return self.group.context

    def reset(self, scenario: Scenario, problem: Problem, rel_cost: float) -> None:
        if scenario.name != self.planner.scenario.name:
            raise ValueError(f"model was trained on {self.planner.scenario.name!r}, not {scenario.name!r}")
        self.scenario, self.problem = scenario, problem
        self.target.reset(scenario, problem)
        self.rtg.reset(scenario, problem)
        self.rtg0 = -self.rtg_scale * rel_cost
        self.spent = 0.0  # Σ c(u) of the executed controls
        self.x = problem.x0
        self.group.join(self.slot)

    def rtg_range(self) -> tuple[float, float]:
        """[μ − 3σ of the model's rtg statistics, −RTG_FLOOR·|rtg_0|]: where training rows' rtg lie."""
        stats = self.planner.stats
        lo = float(stats.mean["rtg"][0] - RTG_SIGMAS * stats.std["rtg"][0])
        hi = -RTG_FLOOR * abs(self.rtg0)
        return min(lo, hi), hi

    def conditioning(self, t: int) -> float | None:
        """The rtg to feed at step t: the rtg mode's, clipped to ``rtg_range`` (None: the context's running value)."""
        value = self.rtg(self, t)
        return None if value is None else float(np.clip(value, *self.rtg_range()))

    def warm_start(self, window: Window, x: np.ndarray) -> WarmStart:
        t0 = time.perf_counter()
        S, U, share, shared = self.group.rollout(self.slot, window)
        X = self.scenario.from_model_states(self.problem, S, start=window.start)
        X[0] = x  # the measured state, exactly (the context holds it in the model dtype)
        ws = WarmStart(X, U, self.target(self.scenario, window, X))
        ws.seconds = time.perf_counter() - t0 - shared + share
        return ws

    def observe(self, u: np.ndarray, x_next: np.ndarray, plan_X: np.ndarray, plan_U: np.ndarray) -> float:
        """Advance the context with the executed control and the measured state; returns the seconds this call spent
        on the group's shared advance (``RolloutGroup.advance``: 0.0 unless it was the step's last member)."""
        self.spent += self.scenario.cost(np.asarray(u)[None])
        self.x = np.asarray(x_next)
        k = self.group.t + 1
        s_next = self.scenario.to_model_states(self.problem, self.x[None], start=k)[0]
        return self.group.advance(self.slot, u, s_next)


class RolloutGroup:
    """One ``RolloutContext`` for the TTO providers of B episodes run in lockstep (``run_mpc_batch``): the B windows
    of a step come from one batched rollout (a batch-1 rollout is a chain of tiny matmuls, so B episodes cost about
    as much as one), and the context advances once every episode has executed its control. Each episode is charged
    its share of the rollout (``WarmStart.seconds``) and of the advance (``Provider.observe``; the loop splits it). A
    ``TTOProvider`` made without a group has one of its own.

    Members may ask windows of different lengths at one step (DAgger draws H per rollout). Each member's
    conditioning is computed once per step, the work its mode shares across members once for all of them
    (``RTGFeed.prepare``: under ``rtg_mode=value`` one batched call of the value output prices every member's
    measured state, each episode charged its share), and a window is the prefix of the step's longest rollout:
    exactly the rollout of its own length, since step k of the autoregressive rollout reads the context and the
    steps before it, never how many follow (``RolloutContext.rollout``: no time-to-go, no terminal step). The
    rollout runs as far as the first request or the step's ``expect``, whichever is longer; a request beyond it runs
    a longer one.

    ``decode_every`` = k (``MPCSettings.decode_every``; 1, the paper's: a decode at every step): the group decodes
    at the episode's first step, when k steps have passed since its last decode, or when a member asks a window
    longer than what remains of it; a decode runs k − 1 steps past the longest window (never past N or the model's
    ``max_steps``), so that the windows until the next decode are its slices: member b's window at step t is row b
    of the last decode from step t − t_decode on. The conditioning is computed at decode steps only (in between the
    context feeds its running value), and the context advances with every executed step, its KV cache extended at
    the next decode in one pass (``RolloutContext.defer_cache``), so each decode conditions on the true history. A
    step without a decode charges no model time to the windows it serves. The members share one schedule: each
    episode is its lone run's when all members ask windows of one length at every step (an evaluation's lockstep
    batch), not when they ask others (DAgger's rollouts, which run k = 1).

    Lifecycle: providers join at construction (``add``: their slot is their row), the context is built when all of
    them have been ``reset`` for an episode, and every member observes once per step (planning before it or not).

    ``decoder`` (``MPCSettings.decoder``): how the context decodes (``RolloutContext``); "fused" is refused here
    (``ValueError``) for a model it cannot run, and when the context is built for a scenario without the fused
    dynamics."""

    def __init__(
        self, planner: Planner, *, use_cache: bool = True, decode_every: int = 1, decoder: str = "torch"
    ) -> None:
        from ttompc.policy.fused import resolve_decoder

        if decode_every < 1:
            raise ValueError(f"decode_every must be >= 1 (a decode every k MPC steps), got {decode_every}")
        if decoder == "fused":  # the model's part now; the scenario's when the context is built
            resolve_decoder(decoder, planner.model, use_cache=use_cache)
        self.planner, self.use_cache, self.decode_every, self.decoder = planner, use_cache, decode_every, decoder
        self.members: list[TTOProvider] = []
        self.context: RolloutContext | None = None
        self._joined: set[int] = set()
        self._pending: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # the current step's shared work: each member's time computing its conditioning, its share of its mode's
        # shared work included ([] until the step decodes), and the longest window expected (``expect``)
        self._own: list[float] = []
        self._expected = 0
        # the last decode: states (B, L+1, n), actions (B, L, m) and 1/B of its time, and the step it started at
        self._plan: tuple[np.ndarray, np.ndarray, float] | None = None
        self._decoded_at = 0

    @property
    def t(self) -> int:
        if self.context is None:
            raise RuntimeError("the rollout group's episodes have not all been reset")
        return self.context.t

    def add(self, member: TTOProvider) -> int:
        if self.context is not None or self._joined:
            raise RuntimeError("providers join a RolloutGroup before its first episode")
        self.members.append(member)
        return len(self.members) - 1

    def join(self, slot: int) -> None:
        """``slot``'s episode is reset; the context starts once every member's is."""
        self._joined.add(slot)
        if len(self._joined) < len(self.members):
            self.context = None
            return
        self._joined.clear()
        self._pending.clear()
        self._new_step()
        self._plan = None
        rtg0 = [m.rtg0 for m in self.members]
        self.context = self.planner.context(
            [m.problem for m in self.members], rtg0=rtg0, ctg0=0.0, use_cache=self.use_cache, decoder=self.decoder
        )
        self.context.defer_cache = self.decode_every > 1  # the cache catches up at the next decode

    def expect(self, start: int, length: int) -> None:
        """The members will ask windows of at most ``length`` steps at step ``start`` (the longest of the lockstep
        windows; 0: no hint): a decode at that step runs that far at once (plus ``decode_every`` − 1 steps), so
        members asking shorter windows share it instead of each running a longer one. A hint only: it changes how
        many rollouts a step runs (with ``decode_every`` > 1 also how far a decode reaches, and so when the next
        one runs), never what a window of a decode gets. Call it at step ``start``, before its first request."""
        if self.context is None or self.context.t != start:
            raise RuntimeError(f"rollout context is at step {getattr(self.context, 't', None)}, not {start}")
        if length < 0:
            raise ValueError(f"expected window length must be >= 0, got {length}")
        self._expected = length

    def rollout(self, slot: int, window: Window) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Row ``slot`` of the last decode, cut to the window (decoding first when the window needs it, class doc):
        its states (H+1, n) and actions (H, m) in the model representation (copies), the member's share of the time
        (at a decode step its own conditioning with its share of its mode's batched work, plus 1/B of the rollout
        that serves it; 0 between decodes) and the time this call spent on the shared work (the members'
        conditioning and the rollout; 0 for a call served by an earlier one's work)."""
        ctx = self.context
        if ctx is None or ctx.t != window.start:
            raise RuntimeError(f"rollout context is at step {getattr(ctx, 't', None)}, not {window.start}")
        t0 = time.perf_counter()
        decoding = self._stale(window)
        if decoding:
            if not self._own:  # the step's first decode: every member's conditioning, once
                self._condition(ctx, window.start)
            t1 = time.perf_counter()
            res = ctx.rollout(self._decode_length(ctx, window))
            self._sync()
            S, A = res.states.double().cpu().numpy(), res.actions.double().cpu().numpy()
            self._plan = (S, A, (time.perf_counter() - t1) / len(self.members))
            self._decoded_at = window.start
        shared = time.perf_counter() - t0 if decoding else 0.0
        assert self._plan is not None  # decoded above when there was none
        S, A, share = self._plan
        j = window.start - self._decoded_at  # the window's first step in the decode
        charge = self._own[slot] + share if j == 0 else 0.0
        # copies: a caller may write into its window (X[0] = x) and the decode serves other windows of this row
        return S[slot, j : j + window.length + 1].copy(), A[slot, j : j + window.length].copy(), charge, shared

    def advance(self, slot: int, u: np.ndarray, s_next: np.ndarray) -> float:
        """Member ``slot`` executed ``u`` and measured ``s_next`` (model representation); the context advances
        when all members have (its KV cache deferred to the next decode when ``decode_every`` > 1). Returns the
        seconds spent on that batched advance (0.0 for a call that only queued its member's part), the work the
        members share (``Provider.observe``)."""
        if self.context is None:
            raise RuntimeError("the rollout group's episodes have not all been reset")
        self._pending[slot] = (np.asarray(u), np.asarray(s_next))
        if len(self._pending) < len(self.members):
            return 0.0
        t0 = time.perf_counter()
        order = range(len(self.members))
        self.context.advance(
            np.stack([self._pending[b][0] for b in order]), np.stack([self._pending[b][1] for b in order])
        )
        self._pending.clear()
        self._new_step()
        self._sync()
        return time.perf_counter() - t0

    def _stale(self, window: Window) -> bool:
        """Whether ``window`` needs a decode: none yet this episode, ``decode_every`` steps since the last, or the
        window runs past what remains of it."""
        if self._plan is None:
            return True
        j = window.start - self._decoded_at
        return j >= self.decode_every or self._plan[1].shape[1] - j < window.length

    def _decode_length(self, ctx: RolloutContext, window: Window) -> int:
        """The steps a decode at ``window``'s step runs: the longest window asked (``expect``) and ``decode_every``
        − 1 steps more, so that the windows until the next decode are its slices, but not past N or the model's
        ``max_steps`` (the window itself is never cut: a window past ``max_steps`` is the rollout's error)."""
        need = max(window.length, self._expected)
        room = min(window.n_total, ctx.model.cfg.max_steps) - window.start
        return max(need, min(need + self.decode_every - 1, room))

    def _condition(self, ctx: RolloutContext, t: int) -> None:
        """Feed every member's conditioning at step t into ``ctx``'s rtg: each mode's shared work for its members in
        one call (``RTGFeed.prepare``), then each member's value. ``_own`` becomes each member's time: its own call
        plus an equal share of its mode's shared work."""
        own = [0.0] * len(self.members)
        modes: dict[type[RTGFeed], list[TTOProvider]] = {}
        for m in self.members:
            modes.setdefault(type(m.rtg), []).append(m)
        for mode, members in modes.items():
            t0 = time.perf_counter()
            mode.prepare(members, t)
            share = (time.perf_counter() - t0) / len(members)
            for m in members:
                own[m.slot] += share
        for m in self.members:
            t0 = time.perf_counter()
            value = m.conditioning(t)
            if value is not None:
                ctx.rtg[m.slot, -1] = value
            own[m.slot] += time.perf_counter() - t0
        self._own = own

    def _new_step(self) -> None:
        """Forget the previous step's conditioning and hint (its decode serves the steps until the next one)."""
        self._own, self._expected = [], 0

    def _sync(self) -> None:
        if self.planner.device.type == "cuda":
            import torch

            torch.cuda.synchronize()
