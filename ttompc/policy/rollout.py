"""Model-based autoregressive rollout of the trajectory transformer (paper §IV-A: model-based generation).

At every step k the transformer reads (goal_k, rtg_k, ctg_k, state_k) after the history and emits a normalised
control; it is de-normalised and propagated with the scenario's approximate model (``Scenario.batched_model``) to
give state_{k+1}; the conditioning is updated (rtg_{k+1} = rtg_k + c(a_k), i.e. minus the reward;
ctg_{k+1} = ctg_k: a plan does not foresee its own violations) and the target is held. The executed history
(``RolloutContext.advance``) counts violations: ctg_{t+1} = ctg_t − violations(s_{t+1}).

One implementation serves open-loop warm starts (start at step 0) and MPC (start at step t after an executed
prefix). ``RolloutContext`` keeps the executed history of B episodes and, with ``use_cache=True``, the KV cache of
that history: each receding-horizon rollout appends its new tokens after the cached history and truncates back to it
at the end, so neither the prefix nor earlier generated steps are ever re-encoded. ``use_cache=False`` re-encodes the
whole prefix at every step like the reference (for timing parity and tests). ``decoder="fused"`` runs the cached
rollout as one compiled call (``ttompc.policy.fused``; ``"auto"``: where it can), and the cache's extension by an
executed step as another, or as none where it claims the token the rollout from that step wrote.

The cached rollout is written for batch-1 latency (a 0.6M-parameter model's step is dispatch-bound, measured in
``bench/rollout_speed.py``): the normalisation is folded into the window's embedding and action head once per
rollout, so a step is one matmul to embed, a ``Decoder`` pass (functional ops, parameters looked up once) and the
dynamics; no module calls, no per-step allocation of the cache.

All tensors going in and out are *un-normalised* and in the scenario's *model* representation; the context
normalises with ``NormStats`` (keys states, actions, goals, rtg, ctg) internally.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ttompc.policy.fused import FusedDecoder, resolve_decoder
from ttompc.policy.gpt import Decoder, KVCache, TrajectoryGPT
from ttompc.policy.stats import NormStats
from ttompc.scenarios.base import BatchedModel, CostNorm


def stage_cost_torch(U: Tensor, norm: CostNorm) -> Tensor:
    """c(u) for controls (..., m) -> (...): the torch twin of ``ttompc.scenarios.base.stage_cost``."""
    if norm == "l1":
        return U.abs().sum(dim=-1)
    if norm == "l2":
        return torch.linalg.vector_norm(U, dim=-1)
    if norm == "quad":
        return 0.5 * (U * U).sum(dim=-1)
    raise ValueError(f"unknown cost norm {norm!r}")


@dataclass
class RolloutResult:
    """A generated window [start, start + H) for B problems (un-normalised, model representation).

    ``states`` (B, H+1, n) with states[:, 0] the measured start state; ``actions`` (B, H, m); ``rtg``/``ctg`` (B, H+1):
    the conditioning fed at steps start..start+H-1, then the value that would follow the last action.
    """

    states: Tensor
    actions: Tensor
    rtg: Tensor
    ctg: Tensor
    start: int


class RolloutContext:
    """Executed history of B episodes plus (optionally) its KV cache, kept across receding-horizon steps.

    Histories: states/goals (B, t+1, ·) (step t is the current, not yet acted-on step), actions (B, t, m),
    rtg/ctg (B, t+1). Build with ``start`` (step 0) or the constructor with a past context (any t0 = t).

    ``defer_cache`` (False: the cache is extended at every ``advance``): ``advance`` only records the step, and the
    next ``rollout`` extends the cache over every step recorded since in one pass, the same tokens (equal up to
    float rounding, not bitwise), for a caller that rolls out every few steps (``RolloutGroup.decode_every``).

    ``decoder`` (``ttompc.policy.config.DECODERS``): "torch" (the default), "fused" (``ttompc.policy.fused``;
    ``ValueError`` where it cannot run) or "auto" (fused where it can). ``decoder`` holds the one that runs and
    ``fallback`` why the torch path runs where "auto" asked for the fused one (None otherwise).
    """

    def __init__(
        self,
        model: TrajectoryGPT,
        stats: NormStats,
        dynamics: BatchedModel,
        cost_norm: CostNorm,
        states: Tensor,
        goals: Tensor,
        rtg: Tensor,
        ctg: Tensor,
        actions: Tensor | None = None,
        *,
        use_cache: bool = True,
        decoder: str = "torch",
    ) -> None:
        p = next(model.parameters())
        self.model, self.stats, self.dynamics, self.cost_norm = model, stats, dynamics, cost_norm
        self.use_cache = use_cache
        self.decoder, self.fallback = resolve_decoder(decoder, model, dynamics, use_cache=use_cache)
        as_t = lambda x: torch.as_tensor(x, dtype=p.dtype, device=p.device)  # noqa: E731
        self.states, self.goals = as_t(states), as_t(goals)
        self.rtg, self.ctg = as_t(rtg), as_t(ctg)
        B, T, n = self.states.shape
        m = model.cfg.control_dim
        self.actions = as_t(actions) if actions is not None else self.states.new_zeros(B, 0, m)
        if self.goals.shape != (B, T, n) or self.rtg.shape != (B, T) or self.ctg.shape != (B, T):
            raise ValueError(
                f"history shapes disagree: states {tuple(self.states.shape)}, goals {tuple(self.goals.shape)}, "
                f"rtg {tuple(self.rtg.shape)}, ctg {tuple(self.ctg.shape)}"
            )
        if self.actions.shape != (B, T - 1, m):
            raise ValueError(f"actions must be (B, {T - 1}, {m}) for {T} states, got {tuple(self.actions.shape)}")
        self._cache: KVCache | None = None  # tokens of the completed steps 0.._cached-1, built on first use
        self._decoder: Decoder | FusedDecoder | None = None  # the trunk over that cache
        self._cached = 0  # the steps the cache holds: t, or fewer after deferred advances
        self.defer_cache = False

    @classmethod
    def start(
        cls,
        model: TrajectoryGPT,
        stats: NormStats,
        dynamics: BatchedModel,
        cost_norm: CostNorm,
        state0: Tensor,
        goal: Tensor,
        rtg0: Tensor | float,
        ctg0: Tensor | float = 0.0,
        *,
        use_cache: bool = True,
        decoder: str = "torch",
    ) -> RolloutContext:
        """Episode start at step 0: state0/goal (B, n), rtg0 (the reference uses −J_REL) and ctg0 (B,) or scalars."""
        state0 = torch.as_tensor(state0)
        B = state0.shape[0]
        col = lambda v: torch.as_tensor(v, dtype=state0.dtype).expand(B).reshape(B, 1)  # noqa: E731
        return cls(
            model,
            stats,
            dynamics,
            cost_norm,
            state0[:, None],
            torch.as_tensor(goal)[:, None],
            col(rtg0),
            col(ctg0),
            use_cache=use_cache,
            decoder=decoder,
        )

    @property
    def t(self) -> int:
        """The current step (the next action to choose is a_t)."""
        return self.states.shape[1] - 1

    @property
    def batch(self) -> int:
        return self.states.shape[0]

    # -------------------------------------------------------------------------------------------- normalisation
    def _norm_step(
        self, goals: Tensor, rtg: Tensor, ctg: Tensor, states: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return (
            self.stats.normalize("goals", goals),
            self.stats.normalize("rtg", rtg[..., None]),
            self.stats.normalize("ctg", ctg[..., None]),
            self.stats.normalize("states", states),
        )

    def _timesteps(self, start: int, stop: int) -> Tensor:
        return torch.arange(start, stop, device=self.states.device).expand(self.batch, -1)

    def _embed_steps(
        self, goals: Tensor, rtg: Tensor, ctg: Tensor, states: Tensor, prev_actions: Tensor, start: int
    ) -> Tensor:
        """The deciding tokens of steps start.. from un-normalised (B, L, ·) values and the L or L-1 previous
        actions (``TrajectoryGPT.embed_steps``)."""
        ts = self._timesteps(start, start + states.shape[1])
        g, r, c, s = self._norm_step(goals, rtg, ctg, states)
        return self.model.embed_steps(g, r, c, s, self.stats.normalize("actions", prev_actions), ts)

    def _history(self) -> Decoder | FusedDecoder:
        """The decoder over the KV cache of the deciding tokens of steps 0..t-1: built at first use, then extended
        over the steps executed since (by ``advance``, or here in one pass for deferred ones). Its parameter look-ups
        are made once per context, which lives for an episode: the model's weights must not change while it lives (the
        cache holds keys and values computed with them; the fused decoder copies them here)."""
        if self._decoder is None:
            self._cache = cache = self.model.new_cache(self.batch)
            fused = self.decoder == "fused"
            self._decoder = (
                FusedDecoder(self.model, self.stats, cache, self.dynamics) if fused else Decoder(self.model, cache)
            )
        c, t, decode = self._cached, self.t, self._decoder
        if c < t and isinstance(decode, FusedDecoder):
            decode.extend(self._inputs(c, t), c)  # claims the last rollout's first token where it is step c's
        elif c < t and isinstance(decode, Decoder):
            prev = self.actions[:, max(c - 1, 0) : t - 1]  # a_{c-1}..a_{t-2}; none before step 0
            decode(
                self._embed_steps(self.goals[:, c:t], self.rtg[:, c:t], self.ctg[:, c:t], self.states[:, c:t], prev, c)
            )
        self._cached = t
        return decode

    def _inputs(self, start: int, stop: int) -> np.ndarray:
        """The un-normalised inputs [goal, rtg, ctg, state, a_{k-1}] of steps start..stop-1 (B, L, 2n+2+m) float32,
        a_{-1} the actions' mean (a normalised zero, as ``embed_steps``): what the fused decoder embeds."""
        prev = self.actions[:, max(start - 1, 0) : stop - 1]
        if start == 0:
            mean = self.stats.mean_std("actions", prev)[0]
            prev = torch.cat([mean.expand(self.batch, 1, -1), prev], dim=1)
        r, c = self.rtg[:, start:stop, None], self.ctg[:, start:stop, None]
        u = torch.cat([self.goals[:, start:stop], r, c, self.states[:, start:stop], prev], dim=2)
        return u.numpy() if u.dtype == torch.float32 else u.to(torch.float32).numpy()

    def _window_maps(self, horizon: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The window's embedding and action head with the normalisation folded in, built once per rollout: the
        tokens of step t+j are ``base[:, j] + z @ W`` for the *un-normalised* z = [rtg, state, a_prev] (B, 1+n+m)
        (``TrajectoryGPT.step_embedding``), and ``F.linear(h, head_w, head_b)`` is the un-normalised action of a
        hidden state h (B, d). -> base (B, H, T·d), W (1+n+m, T·d), head_w (m, d), head_b (m,)."""
        model, stats = self.model, self.stats
        goal = stats.normalize("goals", self.goals[:, -1])
        ctg = stats.normalize("ctg", self.ctg[:, -1:])
        base, W = model.step_embedding(goal, ctg, self.t, horizon)
        # z_norm = (z − μ)/σ, so base + z_norm @ W = (base − (μ/σ) @ W) + z @ (W/σ)
        moments = [stats.mean_std(key, goal) for key in ("rtg", "states", "actions")]
        mu, sd = (torch.cat(parts) for parts in zip(*moments, strict=True))  # (1+n+m,) each
        W = W / sd[:, None]
        base = base - mu @ W
        # a = a_norm·σ_a + μ_a with a_norm = h @ Wᵀ + b
        mu_a, sd_a = stats.mean_std("actions", goal)
        head = model.action_head
        return base, W, head.weight * sd_a[:, None], head.bias * sd_a + mu_a

    # -------------------------------------------------------------------------------------------------- public
    @torch.no_grad()
    def rollout(self, horizon: int) -> RolloutResult:
        """Generate ``horizon`` steps from the current step t after the history (the context is unchanged).

        With the cache, each step embeds its tokens with one matmul (``_window_maps``), runs them through the
        ``Decoder`` after the cached history and truncates the cache back to the history at the end; without it,
        every step re-encodes the whole prefix (``_rollout_full_recompute``). The returned tensors are ordinary
        tensors (the step loop runs under ``inference_mode``; its outputs are stacked outside it)."""
        t0, model = self.t, self.model
        if horizon < 1 or t0 + horizon > model.cfg.max_steps:
            raise ValueError(f"rollout [{t0}, {t0 + horizon}) outside the model's {model.cfg.max_steps} steps")
        if not self.use_cache:
            return self._rollout_full_recompute(horizon)
        decode = self._history()  # outside inference_mode: the cache is written in place by ``advance`` too
        if isinstance(decode, FusedDecoder):
            states, actions, rtg = decode.rollout(self._inputs(t0, t0 + 1)[:, 0], t0, horizon, self.cost_norm)
            return RolloutResult(states, actions, rtg, self.ctg[:, -1:].repeat(1, horizon + 1), t0)
        history = decode.cache.length
        B, T = self.batch, model.cfg.tokens_per_step
        s, r = self.states[:, -1], self.rtg[:, -1:]  # (B, n), (B, 1)
        # a_{t0-1}; at the episode start the action's mean (a normalised zero, like ``embed_steps``)
        a = self.actions[:, -1] if t0 > 0 else self.stats.mean_std("actions", s)[0].expand(B, -1)
        S, A, R = [s], [], [r]
        try:
            with torch.inference_mode():  # the loop's temporaries only; the cache is written in place
                base, W, head_w, head_b = self._window_maps(horizon)
                for j in range(horizon):
                    k = t0 + j
                    tok = torch.addmm(base[:, j], torch.cat([r, s, a], dim=1), W).view(B, T, -1)  # (B, T, d)
                    if k == 0 and model.cfg.layout == "interleaved":
                        tok = tok[:, 1:]  # step 0 has no a_{-1} token
                    a = F.linear(decode(tok)[:, -1], head_w, head_b)  # (B, m), un-normalised
                    s = self.dynamics.step(s, a, k).to(a.dtype)
                    r = r + stage_cost_torch(a, self.cost_norm)[:, None]
                    S.append(s)
                    A.append(a)
                    R.append(r)
        finally:
            decode.cache.truncate(history)
        return RolloutResult(
            states=torch.stack(S, dim=1),
            actions=torch.stack(A, dim=1),
            rtg=torch.cat(R, dim=1),
            ctg=self.ctg[:, -1:].repeat(1, horizon + 1),
            start=t0,
        )

    def _rollout_full_recompute(self, horizon: int) -> RolloutResult:
        """The reference's rollout: every step re-encodes history + generated steps from scratch (teacher-forced
        ``forward``) and reads the action at the last step."""
        t0, model = self.t, self.model
        was_training = model.training
        model.eval()
        try:
            S, R, C = [self.states[:, -1]], [self.rtg[:, -1]], [self.ctg[:, -1]]
            A: list[Tensor] = []
            goal = self.goals[:, -1]  # the target is held over the generated window
            for j in range(horizon):
                a = self.stats.denormalize("actions", self._full_recompute(S, A, R, C, goal))
                A.append(a)
                S.append(self.dynamics.step(S[-1], a, t0 + j).to(a.dtype))
                R.append(R[-1] + stage_cost_torch(a, self.cost_norm))
                C.append(C[-1])
        finally:
            model.train(was_training)
        return RolloutResult(
            states=torch.stack(S, dim=1),
            actions=torch.stack(A, dim=1),
            rtg=torch.stack(R, dim=1),
            ctg=torch.stack(C, dim=1),
            start=t0,
        )

    def _full_recompute(
        self, S: list[Tensor], A: list[Tensor], R: list[Tensor], C: list[Tensor], goal: Tensor
    ) -> Tensor:
        """Reference-style step: encode history + generated steps 0..k from scratch, read the action at step k."""
        cat = lambda hist, new: torch.cat([hist[:, :-1], torch.stack(new, dim=1)], dim=1)  # noqa: E731
        states, rtg, ctg = cat(self.states, S), cat(self.rtg, R), cat(self.ctg, C)
        L = states.shape[1]
        goals = torch.cat([self.goals[:, :-1], goal[:, None].expand(-1, len(S), -1)], dim=1)
        dummy = states.new_zeros(self.batch, 1, self.model.cfg.control_dim)  # a_k: not visible to the state token
        actions = torch.cat([self.actions, *(a[:, None] for a in A), dummy], dim=1)
        g, r, c, s = self._norm_step(goals, rtg, ctg, states)
        a_pred, _ = self.model(g, r, c, s, self.stats.normalize("actions", actions), self._timesteps(0, L))
        return a_pred[:, -1]

    @torch.no_grad()
    def advance(
        self,
        action: Tensor | np.ndarray,
        next_state: Tensor | np.ndarray,
        goal: Tensor | np.ndarray | None = None,
    ) -> None:
        """Record the executed action a_t (B, m) and the measured state s_{t+1} (B, n) (optionally a new goal), as
        tensors or arrays (converted to the model's dtype and device).

        Like the reference MPC context, rtg_{t+1} = rtg_t + c(a_t) and ctg_{t+1} = ctg_t − violations(s_{t+1}). The
        cached history is extended by the deciding tokens of step t (with ``defer_cache``, at the next rollout).
        """
        t = self.t
        p = self.states
        action = torch.as_tensor(action, dtype=p.dtype, device=p.device).reshape(self.batch, -1)
        next_state = torch.as_tensor(next_state, dtype=p.dtype, device=p.device).reshape(self.batch, -1)
        goal = self.goals[:, -1] if goal is None else torch.as_tensor(goal, dtype=p.dtype, device=p.device)
        rtg = self.rtg[:, -1] + stage_cost_torch(action, self.cost_norm)
        ctg = self.ctg[:, -1] - self.dynamics.violations(next_state, t + 1).to(p.dtype)
        self.actions = torch.cat([self.actions, action[:, None]], dim=1)
        self.states = torch.cat([self.states, next_state[:, None]], dim=1)
        self.goals = torch.cat([self.goals, goal[:, None]], dim=1)
        self.rtg = torch.cat([self.rtg, rtg[:, None]], dim=1)
        self.ctg = torch.cat([self.ctg, ctg[:, None]], dim=1)
        if self._decoder is not None and not self.defer_cache:
            self._history()


def rollout(
    model: TrajectoryGPT,
    stats: NormStats,
    dynamics: BatchedModel,
    cost_norm: CostNorm,
    state0: Tensor,
    goal: Tensor,
    rtg0: Tensor | float,
    ctg0: Tensor | float = 0.0,
    horizon: int | None = None,
    *,
    use_cache: bool = True,
) -> RolloutResult:
    """One-shot open-loop rollout from step 0 over ``horizon`` steps (default: the model's ``max_steps``)."""
    ctx = RolloutContext.start(model, stats, dynamics, cost_norm, state0, goal, rtg0, ctg0, use_cache=use_cache)
    return ctx.rollout(horizon or model.cfg.max_steps)
