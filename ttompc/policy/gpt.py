"""A compact causal GPT over trajectory tokens (paper §IV-A), in plain PyTorch, with two token layouts.

Each time step t carries five modalities: goal_t (n), rtg_t (1), ctg_t (1), state_t (n) and action_t (m).

``interleaved`` (the paper's layout, the default) gives each modality a token of its own::

    ... a_{t-1} | g_t  R_t  C_t  s_t | a_t | g_{t+1} ...        (5 tokens per step, 500 for 100 steps)

with one linear embedding per modality. The action head reads the hidden state of the *state* token (it has seen
goal, rtg, ctg and state of step t), the next-state head reads the *action* token.

``stacked`` (a departure, measured in docs/scaling.md) embeds the same five modalities as one token per step::

    ... | [g_t R_t C_t s_t a_{t-1}] | [g_{t+1} ...] ...           (1 token per step, a_{-1} = 0)

The action head reads that token; the next-state head is a small MLP of [hidden_t, a_t]. Attention over 100
instead of 500 tokens makes a training step, the KV cache and MPC re-plans cheaper (measured in docs/design.md).

An optional value output (``value_width`` > 0, a departure: the paper feeds a ledger) predicts the reward-to-go
of step t from (goal, s_t, t) alone, an MLP beside the trunk: the optimal cost-to-go is a function of the state and
the time left, not of the history, and a Markov estimate cannot feed on its own earlier outputs.

In both layouts a learned timestep embedding (the only positional signal) is added to every token; a LayerNorm
(``embed_ln``) and dropout follow; then pre-LN transformer blocks with causal ``scaled_dot_product_attention`` and a
final LayerNorm. ``embed_steps`` makes the tokens that decide the actions of a run of steps, whatever the layout:
the last token's hidden state always decides the last step's action. Because positions are carried by the timestep
embedding only, the token stream can be fed in any chunks: a ``KVCache`` keeps the keys/values of the tokens seen
so far and ``encode(tokens, cache)`` processes only the new ones. That is what makes a 100-step rollout cost
O(steps) forward work instead of O(steps²) (the reference re-encodes the whole prefix every step).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ttompc.policy.config import ModelConfig

_ACTIVATIONS = {"relu": nn.ReLU, "gelu": nn.GELU, "silu": nn.SiLU}


class KVCache:
    """Preallocated keys/values per layer, (B, heads, capacity, head_dim) with capacity ``cfg.max_tokens`` (tokens
    per step × max_steps) unless given, and the number of tokens filled.

    ``fork()`` copies the filled prefix so a speculative rollout can extend the copy while the original (e.g. the
    executed MPC history) stays untouched.
    """

    def __init__(
        self,
        cfg: ModelConfig,
        batch: int,
        dtype: torch.dtype,
        device: torch.device | str,
        capacity: int | None = None,
    ) -> None:
        head_dim = cfg.n_embd // cfg.n_head
        self.cfg = cfg
        shape = (cfg.n_layer, batch, cfg.n_head, capacity or cfg.max_tokens, head_dim)
        self.k = torch.zeros(shape, dtype=dtype, device=device)
        self.v = torch.zeros(shape, dtype=dtype, device=device)
        self.length = 0

    @property
    def capacity(self) -> int:
        return self.k.shape[3]

    def append(self, layer: int, k: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """Write the new keys/values (B, h, T, d) after the filled prefix; return all of them (B, h, length+T, d).
        ``length`` is advanced once per forward by ``advance`` (all layers append the same T tokens)."""
        end = self.length + k.shape[2]
        if end > self.capacity:
            raise ValueError(f"KV cache overflow: {end} tokens > capacity {self.capacity} (max_steps too small)")
        self.k[layer, :, :, self.length : end] = k
        self.v[layer, :, :, self.length : end] = v
        return self.k[layer, :, :, :end], self.v[layer, :, :, :end]

    def advance(self, n_tokens: int) -> None:
        self.length += n_tokens

    def fork(self, extra_tokens: int | None = None) -> KVCache:
        """A copy of the filled prefix with room for ``extra_tokens`` more (default: the parent's capacity), so
        short MPC rollouts do not allocate a full-length cache."""
        capacity = self.capacity if extra_tokens is None else min(self.length + extra_tokens, self.cfg.max_tokens)
        new = KVCache(self.cfg, self.k.shape[1], self.k.dtype, self.k.device, capacity=capacity)
        new.k[:, :, :, : self.length] = self.k[:, :, :, : self.length]
        new.v[:, :, :, : self.length] = self.v[:, :, :, : self.length]
        new.length = self.length
        return new


class CausalSelfAttention(nn.Module):
    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.n_head = cfg.n_head
        self.qkv = nn.Linear(cfg.n_embd, 3 * cfg.n_embd, bias=cfg.bias)
        self.proj = nn.Linear(cfg.n_embd, cfg.n_embd, bias=cfg.bias)
        self.dropout = cfg.dropout if cfg.attn_dropout is None else cfg.attn_dropout
        self.resid_drop = nn.Dropout(cfg.dropout)

    def forward(self, x: Tensor, layer: int, cache: KVCache | None) -> Tensor:
        B, T, C = x.shape
        q, k, v = self.qkv(x).split(C, dim=2)  # 3 × (B, T, C)
        q, k, v = (z.view(B, T, self.n_head, C // self.n_head).transpose(1, 2) for z in (q, k, v))  # (B, h, T, d)
        past = 0
        if cache is not None:
            past = cache.length
            k, v = cache.append(layer, k, v)  # (B, h, past+T, d)
        p = self.dropout if self.training else 0.0
        if past == 0 or T == 1:
            # No prefix: ordinary causal mask. One new token: it may attend to everything cached.
            y = F.scaled_dot_product_attention(q, k, v, dropout_p=p, is_causal=past == 0 and T > 1)
        else:
            # T new tokens after `past` cached ones: query i (absolute past+i) sees keys 0..past+i.
            mask = torch.ones(T, past + T, dtype=torch.bool, device=x.device).tril(diagonal=past)
            y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p)
        y = y.transpose(1, 2).reshape(B, T, C)  # (B, T, C)
        return self.resid_drop(self.proj(y))


class Block(nn.Module):
    """Pre-LN transformer block: x + attn(ln(x)), then x + mlp(ln(x))."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.ln_1 = nn.LayerNorm(cfg.n_embd, bias=cfg.bias)
        self.attn = CausalSelfAttention(cfg)
        self.ln_2 = nn.LayerNorm(cfg.n_embd, bias=cfg.bias)
        hidden = cfg.mlp_ratio * cfg.n_embd
        self.mlp = nn.Sequential(
            nn.Linear(cfg.n_embd, hidden, bias=cfg.bias),
            _ACTIVATIONS[cfg.activation](),
            nn.Linear(hidden, cfg.n_embd, bias=cfg.bias),
            nn.Dropout(cfg.dropout),
        )

    def forward(self, x: Tensor, layer: int, cache: KVCache | None) -> Tensor:
        x = x + self.attn(self.ln_1(x), layer, cache)
        return x + self.mlp(self.ln_2(x))


class TrajectoryGPT(nn.Module):
    """The trajectory transformer. ``forward`` is the teacher-forced training path over full steps; ``encode`` with
    ``embed_steps`` is the token-level path used (with a ``KVCache``) by the autoregressive rollout."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        n, m, d = cfg.state_dim, cfg.control_dim, cfg.n_embd
        if cfg.layout == "interleaved":
            self.embed_goal = nn.Linear(n, d)
            self.embed_rtg = nn.Linear(1, d)
            self.embed_ctg = nn.Linear(1, d)
            self.embed_state = nn.Linear(n, d)
            self.embed_action = nn.Linear(m, d)
        else:  # stacked: [goal, rtg, ctg, state, previous action] -> one token
            self.embed_stacked = nn.Linear(2 * n + 2 + m, d)
        self.embed_timestep = nn.Embedding(cfg.max_steps, d)
        self.embed_ln = nn.LayerNorm(d, bias=cfg.bias)
        self.drop = nn.Dropout(cfg.dropout)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layer))
        self.ln_f = nn.LayerNorm(d, bias=cfg.bias)
        self.action_head = nn.Linear(d, m)
        self.state_head: nn.Module
        if cfg.layout == "interleaved":
            self.state_head = nn.Linear(d, n)
        else:  # the step's token has not seen a_t: the head reads it beside the hidden state
            self.state_head = nn.Sequential(nn.Linear(d + m, d), _ACTIVATIONS[cfg.activation](), nn.Linear(d, n))
        self.value_head: nn.Module | None = None
        if cfg.value_width > 0:
            w, act = cfg.value_width, _ACTIVATIONS[cfg.activation]
            self.value_head = nn.Sequential(nn.Linear(2 * n + 1, w), act(), nn.Linear(w, w), act(), nn.Linear(w, 1))
        self.apply(self._init_weights)
        # GPT-2 scaled init of residual projections keeps the residual stream's variance independent of depth.
        for name, p in self.named_parameters():
            if name.endswith("attn.proj.weight") or name.endswith("mlp.2.weight"):
                nn.init.normal_(p, mean=0.0, std=cfg.init_std / math.sqrt(2 * cfg.n_layer))

    def _init_weights(self, module: nn.Module) -> None:
        if isinstance(module, (nn.Linear, nn.Embedding)):
            nn.init.normal_(module.weight, mean=0.0, std=self.cfg.init_std)
            if isinstance(module, nn.Linear) and module.bias is not None:
                nn.init.zeros_(module.bias)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def value(self, goals: Tensor, states: Tensor, timesteps: Tensor) -> Tensor:
        """The value output: normalised goals/states (B, L, n), timesteps (B, L) int -> the predicted normalised
        reward-to-go (B, L, 1) of an optimal plan from s_t at step t. Raises if the model has none."""
        if self.value_head is None:
            raise ValueError("this model has no value output (model.value_width = 0)")
        t = (timesteps.to(states.dtype) / self.cfg.max_steps).unsqueeze(-1)  # (B, L, 1), in [0, 1)
        return self.value_head(torch.cat([goals, states, t], dim=-1))

    # ------------------------------------------------------------------------------------------ token embeddings
    def embed_steps(
        self, goals: Tensor, rtg: Tensor, ctg: Tensor, states: Tensor, prev_actions: Tensor, timesteps: Tensor
    ) -> Tensor:
        """The tokens that decide the actions of L consecutive steps k0..k0+L-1 (all normalised): goals/states
        (B, L, n), rtg/ctg (B, L, 1), timesteps (B, L) int, prev_actions (B, L, m) = a_{k-1} of each step, or
        (B, L-1, m) when the first step has none (the start of a sequence). The hidden state of the last token
        decides the last step's action.

        -> interleaved (B, 5L, d): a_{k-1} g_k R_k C_k s_k per step (a_{k0-1} left out when not given);
        -> stacked (B, L, d): one token per step (a missing a_{k0-1} is zero)."""
        L = timesteps.shape[1]
        if prev_actions.shape[1] not in (L - 1, L):
            raise ValueError(f"prev_actions must hold {L - 1} or {L} steps for {L} steps, got {prev_actions.shape[1]}")
        first_missing = prev_actions.shape[1] == L - 1
        if first_missing:
            prev_actions = F.pad(prev_actions, (0, 0, 1, 0))  # (B, L, m), a zero a_{k0-1}
        t = self.embed_timestep(timesteps)  # (B, L, d)
        if self.cfg.layout == "stacked":
            return self.embed_stacked(torch.cat([goals, rtg, ctg, states, prev_actions], dim=-1)) + t  # (B, L, d)
        act = self.embed_action(prev_actions) + self.embed_timestep((timesteps - 1).clamp_min(0))  # a_{k-1} at k-1
        toks = (act, self.embed_goal(goals) + t, self.embed_rtg(rtg) + t, self.embed_ctg(ctg) + t)
        x = torch.stack([*toks, self.embed_state(states) + t], dim=2).flatten(1, 2)  # (B, 5L, d)
        return x[:, 1:] if first_missing else x

    # ------------------------------------------------------------------------------------------------- trunk
    def encode(self, tokens: Tensor, cache: KVCache | None = None) -> Tensor:
        """Embedded tokens (B, T, d) -> final hidden states (B, T, d). With a cache the T tokens are appended after
        the cached ones and attend to them; the cache length advances by T."""
        x = self.drop(self.embed_ln(tokens))
        for i, block in enumerate(self.blocks):
            x = block(x, i, cache)
        if cache is not None:
            cache.advance(tokens.shape[1])
        return self.ln_f(x)

    def new_cache(self, batch: int, capacity: int | None = None) -> KVCache:
        p = next(self.parameters())
        return KVCache(self.cfg, batch, dtype=p.dtype, device=p.device, capacity=capacity)

    # ------------------------------------------------------------------------------------------ training path
    def forward(
        self,
        goals: Tensor,
        rtg: Tensor,
        ctg: Tensor,
        states: Tensor,
        actions: Tensor,
        timesteps: Tensor,
    ) -> tuple[Tensor, Tensor]:
        """Teacher-forced predictions for L steps (all inputs normalised, shapes as in ``embed_steps``; actions
        (B, L, m) = a_k of each step). Returns (action_preds (B, L, m), next_state_preds (B, L, n)); the action of
        step k sees nothing of a_k or later, the next state of step k sees a_k."""
        B, L = timesteps.shape
        if L > self.cfg.max_steps:
            raise ValueError(f"sequence of {L} steps exceeds max_steps={self.cfg.max_steps}")
        x = self.embed_steps(goals, rtg, ctg, states, actions[:, :-1], timesteps)
        if self.cfg.layout == "stacked":
            h = self.encode(x)  # (B, L, d)
            return self.action_head(h), self.state_head(torch.cat([h, actions], dim=-1))
        last = self.embed_action(actions[:, -1:]) + self.embed_timestep(timesteps[:, -1:])  # reads s_L
        h = self.encode(torch.cat([x, last], dim=1)).view(B, L, 5, -1)  # (B, L, 5, d): g R C s a per step
        return self.action_head(h[:, :, 3]), self.state_head(h[:, :, 4])
