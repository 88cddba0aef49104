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
the time left, not of the history, and a Markov estimate cannot feed on its own earlier outputs. Its forms and its
local model for an MPC window's terminal cost: ``ttompc.policy.value``.

In both layouts a learned timestep embedding (the only positional signal) is added to every token; a LayerNorm
(``embed_ln``) and dropout follow; then pre-LN transformer blocks with causal ``scaled_dot_product_attention`` and a
final LayerNorm. ``embed_steps`` makes the tokens that decide the actions of a run of steps, whatever the layout:
the last token's hidden state always decides the last step's action. Because positions are carried by the timestep
embedding only, the token stream can be fed in any chunks: a ``KVCache`` keeps the keys/values of the tokens seen
so far and ``encode(tokens, cache)`` processes only the new ones. That is what makes a 100-step rollout cost
O(steps) forward work instead of O(steps²) (the reference re-encodes the whole prefix every step). ``Decoder`` is
the same cached pass for inference in functional ops, what rollouts run (``encode`` with a cache is its readable
reference, and the baseline of ``bench/rollout_speed.py``); ``step_embedding`` is ``embed_steps`` of a planning
window as one affine map, so a rollout step embeds its tokens with one matmul.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ttompc.policy.config import ModelConfig
from ttompc.policy.value import ACTIVATIONS as _ACTIVATIONS
from ttompc.policy.value import build_value_head

# the same, as functions (``Decoder``)
_ACTIVATION_FNS: dict[str, Callable[[Tensor], Tensor]] = {"relu": F.relu, "gelu": F.gelu, "silu": F.silu}


class KVCache:
    """Preallocated keys/values per layer, (n_layer, B, heads, capacity, head_dim) with capacity ``cfg.max_tokens``
    (tokens per step × max_steps), and the number of tokens filled. Appends write in place; nothing grows."""

    def __init__(self, cfg: ModelConfig, batch: int, dtype: torch.dtype, device: torch.device | str) -> None:
        head_dim = cfg.n_embd // cfg.n_head
        self.cfg = cfg
        shape = (cfg.n_layer, batch, cfg.n_head, cfg.max_tokens, head_dim)
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

    def truncate(self, length: int) -> None:
        """Forget the tokens after the first ``length``: a speculative rollout appends after the executed history and
        then truncates back to it (the slots past ``length`` are scratch, overwritten by the next append)."""
        if not 0 <= length <= self.length:
            raise ValueError(f"cannot truncate a cache of {self.length} tokens to {length}")
        self.length = length


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


class Decoder:
    """The trunk over a ``KVCache``, for inference: ``decoder(tokens)`` computes what ``model.encode(tokens, cache)``
    of an eval-mode model computes (no dropout, whatever the model's mode), in functional ops. Call it under
    ``torch.no_grad`` or ``inference_mode``.

    A rollout step of a small model is dispatch-bound at batch 1: ~20 small ops per layer, where a module call costs
    ~5 µs and a parameter look-up ~1.5 µs beside ~7 µs for a 128×384 matvec (measured on the 2-core dev VM). So the
    decoder looks the parameters up once, at construction, and holds the model's parameter tensors: in-place updates
    (an optimizer step, ``load_state_dict``) are seen; replaced parameters (a model moved to another device or
    dtype) need a new decoder.
    """

    def __init__(self, model: TrajectoryGPT, cache: KVCache) -> None:
        cfg = model.cfg
        self.cache = cache
        self.n_head, self.act = cfg.n_head, _ACTIVATION_FNS[cfg.activation]
        self.embed_ln = (model.embed_ln.weight, model.embed_ln.bias)
        self.ln_f = (model.ln_f.weight, model.ln_f.bias)
        # per layer: weight and bias of ln_1, qkv, proj, ln_2, mlp in, mlp out (a bias None without cfg.bias), and the
        # layer's cache slices k, v (B, h, capacity, hd)
        self.layers: list[tuple[tuple[Any, ...], Tensor, Tensor]] = []
        for i, block in enumerate(cast(list[Block], model.blocks)):
            mods = (block.ln_1, block.attn.qkv, block.attn.proj, block.ln_2, block.mlp[0], block.mlp[2])
            self.layers.append((tuple(t for mod in mods for t in (mod.weight, mod.bias)), cache.k[i], cache.v[i]))

    def __call__(self, tokens: Tensor) -> Tensor:
        """Embedded tokens (B, T, d) -> final hidden states (B, T, d); the T tokens are appended after the cached ones,
        attend to them and to each other causally, and the cache length advances by T."""
        B, T, C = tokens.shape
        start, end = self.cache.length, self.cache.length + T
        if end > self.cache.capacity:
            raise ValueError(f"KV cache overflow: {end} tokens > capacity {self.cache.capacity} (max_steps too small)")
        # query i (absolute start+i) sees keys 0..start+i; one new token sees everything (no mask needed)
        mask = None if T == 1 else torch.ones(T, end, dtype=torch.bool, device=tokens.device).tril(diagonal=start)
        x = F.layer_norm(tokens, (C,), *self.embed_ln)
        for weights, k_cache, v_cache in self.layers:
            ln1_w, ln1_b, qkv_w, qkv_b, proj_w, proj_b, ln2_w, ln2_b, fc_w, fc_b, out_w, out_b = weights
            qkv = F.linear(F.layer_norm(x, (C,), ln1_w, ln1_b), qkv_w, qkv_b)  # (B, T, 3C)
            q, k, v = qkv.view(B, T, 3, self.n_head, C // self.n_head).permute(2, 0, 3, 1, 4).unbind(0)  # (B, h, T, hd)
            k_cache.narrow(2, start, T).copy_(k)
            v_cache.narrow(2, start, T).copy_(v)
            y = F.scaled_dot_product_attention(q, k_cache.narrow(2, 0, end), v_cache.narrow(2, 0, end), attn_mask=mask)
            x = x + F.linear(y.transpose(1, 2).reshape(B, T, C), proj_w, proj_b)
            x = x + F.linear(self.act(F.linear(F.layer_norm(x, (C,), ln2_w, ln2_b), fc_w, fc_b)), out_w, out_b)
        self.cache.length = end
        return F.layer_norm(x, (C,), *self.ln_f)


class TrajectoryGPT(nn.Module):
    """The trajectory transformer. ``forward`` is the teacher-forced training path over full steps; ``embed_steps``
    and ``encode`` (with a ``KVCache``; ``Decoder`` is its fast twin) are the token-level path of the autoregressive
    rollout, ``step_embedding`` the embedding of a planning window as one affine map."""

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
        self.value_head = build_value_head(cfg)  # ttompc.policy.value; None without a value output
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

    def step_embedding(self, goal: Tensor, ctg: Tensor, start: int, horizon: int) -> tuple[Tensor, Tensor]:
        """``embed_steps`` of the steps k = start..start+horizon-1 of a window that holds goal (B, n) and ctg (B, 1)
        (normalised), as an affine map of what changes from step to step, z_k = [rtg_k, state_k, a_{k-1}]
        (B, 1+n+m, normalised): the T = ``tokens_per_step`` tokens of step k are (base[:, k-start] + z_k @ W) viewed
        (B, T, d). At step 0 (no a_{-1}) feed a zero a_{-1}; the interleaved layout then drops the first token.

        -> base (B, horizon, T·d), W (1+n+m, T·d)."""
        n, m, d = self.cfg.state_dim, self.cfg.control_dim, self.cfg.n_embd
        steps = torch.arange(start, start + horizon, device=goal.device)
        t = self.embed_timestep(steps)  # (H, d)
        if self.cfg.layout == "stacked":  # one token [g, R, C, s, a_{k-1}]
            w_g, w_r, w_c, w_s, w_a = self.embed_stacked.weight.split([n, 1, 1, n, m], dim=1)  # (d, ·) each
            base = (F.linear(goal, w_g) + F.linear(ctg, w_c, self.embed_stacked.bias))[:, None] + t  # (B, H, d)
            return base, torch.cat([w_r, w_s, w_a], dim=1).T
        # interleaved: tokens a_{k-1} g_k R_k C_k s_k, the action token at step k-1
        act = self.embed_action.bias + self.embed_timestep((steps - 1).clamp_min(0))
        B = goal.shape[0]
        toks = (act, self.embed_goal(goal)[:, None] + t, self.embed_rtg.bias + t, self.embed_ctg(ctg)[:, None] + t)
        base = torch.stack([x.expand(B, horizon, d) for x in (*toks, self.embed_state.bias + t)], dim=2)  # (B, H, 5, d)
        W = goal.new_zeros(1 + n + m, 5, d)
        W[0, 2] = self.embed_rtg.weight[:, 0]
        W[1 : 1 + n, 4] = self.embed_state.weight.T
        W[1 + n :, 0] = self.embed_action.weight.T
        return base.flatten(2), W.flatten(1)

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

    def new_cache(self, batch: int) -> KVCache:
        p = next(self.parameters())
        return KVCache(self.cfg, batch, dtype=p.dtype, device=p.device)

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
