"""A compact causal GPT over interleaved trajectory tokens (paper §IV-A, fact sheet §2), in plain PyTorch.

Each time step t contributes five tokens, in this order::

    goal_t (n) | rtg_t (1) | ctg_t (1) | state_t (n) | action_t (m)

Every modality has its own linear embedding; a learned timestep embedding (the only positional signal) is added to
all five tokens of a step; a LayerNorm (``embed_ln``) and dropout follow; then pre-LN transformer blocks with causal
``scaled_dot_product_attention`` and a final LayerNorm. The action head reads the hidden state of the *state* token
(it has seen goal, rtg, ctg and state of step t), the next-state head reads the *action* token.

Because positions are carried by the timestep embedding only, the token stream can be fed in any chunks: a
``KVCache`` keeps the keys/values of the tokens seen so far and ``encode(tokens, cache)`` processes only the new
ones. That is what makes a 100-step rollout cost O(steps) forward work instead of O(steps²) (the reference re-encodes
the whole prefix every step).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ttompc.policy.config import TOKENS_PER_STEP, ModelConfig

_ACTIVATIONS = {"relu": nn.ReLU, "gelu": nn.GELU, "silu": nn.SiLU}


class KVCache:
    """Preallocated keys/values per layer, (B, heads, capacity, head_dim) with capacity 5·max_steps unless given,
    and the number of tokens filled.

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
    the ``embed_*`` helpers is the token-level path used (with a ``KVCache``) by the autoregressive rollout."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        n, m, d = cfg.state_dim, cfg.control_dim, cfg.n_embd
        self.embed_goal = nn.Linear(n, d)
        self.embed_rtg = nn.Linear(1, d)
        self.embed_ctg = nn.Linear(1, d)
        self.embed_state = nn.Linear(n, d)
        self.embed_action = nn.Linear(m, d)
        self.embed_timestep = nn.Embedding(cfg.max_steps, d)
        self.embed_ln = nn.LayerNorm(d, bias=cfg.bias)
        self.drop = nn.Dropout(cfg.dropout)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layer))
        self.ln_f = nn.LayerNorm(d, bias=cfg.bias)
        self.action_head = nn.Linear(d, m)
        self.state_head = nn.Linear(d, n)
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

    # ------------------------------------------------------------------------------------------ token embeddings
    def embed_step(self, goals: Tensor, rtg: Tensor, ctg: Tensor, states: Tensor, timesteps: Tensor) -> Tensor:
        """The first four tokens of each step: goals/states (B, L, n), rtg/ctg (B, L, 1), timesteps (B, L) int
        -> (B, 4L, d) interleaved as g_0 R_0 C_0 s_0 g_1 ..."""
        t = self.embed_timestep(timesteps)  # (B, L, d)
        toks = (self.embed_goal(goals), self.embed_rtg(rtg), self.embed_ctg(ctg), self.embed_state(states))
        x = torch.stack([e + t for e in toks], dim=2)  # (B, L, 4, d)
        return x.flatten(1, 2)  # (B, 4L, d)

    def embed_actions(self, actions: Tensor, timesteps: Tensor) -> Tensor:
        """Action tokens: actions (B, L, m), timesteps (B, L) -> (B, L, d)."""
        return self.embed_action(actions) + self.embed_timestep(timesteps)

    def embed_sequence(
        self, goals: Tensor, rtg: Tensor, ctg: Tensor, states: Tensor, actions: Tensor, timesteps: Tensor
    ) -> Tensor:
        """Full steps -> (B, 5L, d) interleaved g R C s a per step."""
        B, L = timesteps.shape
        four = self.embed_step(goals, rtg, ctg, states, timesteps).view(B, L, 4, -1)  # (B, L, 4, d)
        act = self.embed_actions(actions, timesteps).unsqueeze(2)  # (B, L, 1, d)
        return torch.cat([four, act], dim=2).flatten(1, 2)  # (B, 5L, d)

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
        """Teacher-forced predictions for L steps (all inputs normalised, shapes as in ``embed_step``; actions
        (B, L, m)). Returns (action_preds (B, L, m) read at state tokens, next_state_preds (B, L, n) read at action
        tokens)."""
        B, L = timesteps.shape
        if L > self.cfg.max_steps:
            raise ValueError(f"sequence of {L} steps exceeds max_steps={self.cfg.max_steps}")
        h = self.encode(self.embed_sequence(goals, rtg, ctg, states, actions, timesteps))  # (B, 5L, d)
        h = h.view(B, L, TOKENS_PER_STEP, -1)  # (B, L, 5, d)
        return self.action_head(h[:, :, 3]), self.state_head(h[:, :, 4])
