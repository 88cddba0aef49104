"""The fused decode (``RolloutContext(..., decoder="fused")``, ``MPCSettings.decoder``): a cached rollout's whole
H-step generation in one compiled call, and the KV-cache extension of ``advance`` in another.

The torch rollout of a small model is dispatch-bound (``bench/model_calls.py``: ~60 torch ops per generated step,
the matmul arithmetic 10–18% of the time). ``FusedDecoder`` runs the same computation in numba
(``ttompc.policy.fused_kernel``), float32 like the torch path: per generated step the window embedding
(``RolloutContext._window_maps``, built in torch once per rollout), the decoder layers over the cached history and
the generated tokens, the action head, the scenario's approximate dynamics (``BatchedModel.fused_step``) and the
rtg update with the stage cost. It reads and writes the KV cache the torch ``Decoder`` would (zero-copy numpy views
of ``KVCache.k``/``v``): a rollout writes its tokens into the free slots after the history and leaves ``length``
alone (what the torch path truncates back to), an extension writes its tokens and advances ``length``, so the
torch and fused decoders can take turns on one cache. The results equal the torch path's up to float rounding
(``tests/test_fused_decode.py``), not bitwise.

It runs the ``stacked`` layout with a relu, gelu or silu MLP, a float32 model on the CPU, with the KV cache, and a
scenario whose batched model has ``fused_step`` (the three built-in ones). Elsewhere ``decoder="fused"`` raises
``ValueError`` naming the reason, and ``decoder="auto"`` runs the torch path, with the reason in
``RolloutContext.fallback`` and a ``RuntimeWarning`` (``resolve_decoder``). The weights are copied into the kernel's
layout (``fused_kernel.TrunkWeights``) when the decoder is built, with its context: the rule of ``RolloutContext``,
that the model's weights do not change while a context lives (its KV cache holds keys and values computed with
them), makes watching them for changes unnecessary; a context built after an optimizer step or ``load_state_dict``
computes with the new weights. The value output is not fused: it is one
small MLP call per MPC step outside the rollout (``Planner.cost_to_go``, its numbers in ``bench/model_calls.py``).

First use compiles the kernels and the scenario's dynamics step (about 12 s on the dev VM), cached on disk by numba
(``NUMBA_CACHE_DIR`` or the package's ``__pycache__``): later processes load them (about 0.4 s).
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch
from torch import Tensor, nn

from ttompc.policy.config import DECODERS
from ttompc.policy.gpt import Block, KVCache, TrajectoryGPT
from ttompc.scenarios.base import BatchedModel, CostNorm

if TYPE_CHECKING:
    from ttompc.policy.fused_kernel import TrunkWeights


def fused_support(model: TrajectoryGPT, dynamics: BatchedModel | None = None, *, use_cache: bool = True) -> str | None:
    """Why the fused kernel cannot run ``model`` (with ``dynamics``, when given), one sentence; None when it can."""
    from ttompc.policy.fused_kernel import ACT_CODES

    cfg, p = model.cfg, next(model.parameters())
    if cfg.layout != "stacked":
        return f"the fused decode runs the stacked layout only (this model's is {cfg.layout!r})"
    if cfg.activation not in ACT_CODES:
        return f"the fused decode has no {cfg.activation!r} activation (it has {sorted(ACT_CODES)})"
    if p.device.type != "cpu" or p.dtype != torch.float32:
        return f"the fused decode runs float32 models on the CPU (this one is {p.dtype} on {p.device})"
    if not use_cache:
        return "the fused decode extends the KV cache (use_cache=False re-encodes the prefix at every step)"
    if dynamics is not None and not callable(getattr(dynamics, "fused_step", None)):
        return f"the scenario's batched model ({type(dynamics).__name__}) has no fused_step (BatchedModel)"
    return None


def resolve_decoder(
    decoder: str, model: TrajectoryGPT, dynamics: BatchedModel | None = None, *, use_cache: bool = True
) -> tuple[str, str | None]:
    """The decoder a context runs for the requested one (``DECODERS``) -> ("torch" or "fused", why the torch path
    runs where ``auto`` asked for the fused one, else None). ``auto`` falling back warns once per reason; raises
    ``ValueError`` for an unknown name, and for ``fused`` where it cannot run (``fused_support``)."""
    if decoder not in DECODERS:
        raise ValueError(f"decoder must be one of {list(DECODERS)}, got {decoder!r}")
    if decoder == "torch":
        return "torch", None
    reason = fused_support(model, dynamics, use_cache=use_cache)
    if reason is None:
        return "fused", None
    if decoder == "fused":
        raise ValueError(f"decoder='fused' cannot run here: {reason}; use decoder='torch' (or 'auto')")
    warnings.warn(f"decoder='auto' runs the torch decode: {reason}", RuntimeWarning, stacklevel=3)
    return "torch", reason


def _numpy(t: Tensor) -> np.ndarray:
    """A float32 C-contiguous numpy view of ``t`` (a copy only where ``t`` is not already one)."""
    t = t.detach()
    return (t if t.dtype == torch.float32 and t.is_contiguous() else t.to(torch.float32).contiguous()).numpy()


def trunk_weights(model: TrajectoryGPT) -> TrunkWeights:
    """A copy of the trunk's parameters in the kernel's layout (``fused_kernel.TrunkWeights``; a float32 model on the
    CPU): linear weights transposed, zeros for the biases a module has none of."""
    from ttompc.policy.fused_kernel import LayerWeights, TrunkWeights

    def bias(b: Tensor | None, size: int) -> np.ndarray:
        return np.zeros(size, np.float32) if b is None else _numpy(b).copy()

    def norm(mod: nn.LayerNorm) -> tuple[np.ndarray, np.ndarray]:
        return _numpy(mod.weight).copy(), bias(mod.bias, mod.weight.shape[0])

    def linear(mod: nn.Module) -> tuple[np.ndarray, np.ndarray]:
        lin = cast(nn.Linear, mod)
        return _numpy(lin.weight.T), bias(lin.bias, lin.out_features)

    layers = tuple(
        LayerWeights(
            *norm(b.ln_1),
            *linear(b.attn.qkv),
            *linear(b.attn.proj),
            *norm(b.ln_2),
            *linear(b.mlp[0]),
            *linear(b.mlp[2]),
        )
        for b in cast(list[Block], list(model.blocks))
    )
    return TrunkWeights(*norm(model.embed_ln), *norm(model.ln_f), layers)


class FusedDecoder:
    """The trunk over a ``KVCache`` and the rollout, in one numba call each; ``decoder(tokens)`` has the contract of
    ``Decoder.__call__`` (what ``RolloutContext`` extends its history with), ``rollout`` generates a window.

    ``dynamics`` is the context's batched model (B problems, the cache's batch); its ``fused_step`` is read once,
    the model's weights copied once (``trunk_weights``)."""

    def __init__(self, model: TrajectoryGPT, cache: KVCache, dynamics: BatchedModel) -> None:
        from ttompc.policy.fused_kernel import ACT_CODES

        self.model, self.cache = model, cache
        cfg = model.cfg
        self.n_head, self.act = cfg.n_head, ACT_CODES[cfg.activation]
        self.weights = trunk_weights(model)
        self.K, self.V = cache.k.numpy(), cache.v.numpy()  # (L, B, heads, capacity, hd) views, written in place
        self.step, self.params = cast(Any, dynamics).fused_step()  # the cfunc and its rows (B, P)
        if self.params.shape[0] != self.K.shape[1] or self.params.dtype != np.float32:
            raise ValueError(f"fused_step params must be float32 (B={self.K.shape[1]}, P), got {self.params.shape}")

    def _room(self, tokens: int) -> int:
        start = self.cache.length
        if start + tokens > self.cache.capacity:
            raise ValueError(f"KV cache overflow: {start + tokens} tokens > capacity {self.cache.capacity}")
        return start

    def __call__(self, tokens: Tensor) -> Tensor:
        """Embedded tokens (B, T, d) -> final hidden states (B, T, d), appended after the cached ones (the cache
        length advances by T), as ``Decoder.__call__``."""
        from ttompc.policy.fused_kernel import extend_kernel

        start = self._room(tokens.shape[1])
        out = np.empty(tokens.shape, np.float32)
        extend_kernel(self.n_head, self.act, self.weights, self.K, self.V, start, _numpy(tokens), out)
        self.cache.length = start + tokens.shape[1]
        return torch.from_numpy(out)

    def rollout(
        self,
        maps: tuple[Tensor, Tensor, Tensor, Tensor],
        state: Tensor,
        rtg: Tensor,
        prev_action: Tensor,
        start: int,
        cost_norm: CostNorm,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The H = maps[0].shape[1] steps from step ``start`` after the cached history (whose length is left as it
        is; its free slots are scratch). ``maps``: ``RolloutContext._window_maps``; state (B, n), rtg (B,) and
        prev_action (B, m) = a_{start-1}, un-normalised. -> states (B, H+1, n), actions (B, H, m), rtg (B, H+1)."""
        from ttompc.policy.fused_kernel import COST_CODES, WindowMaps, rollout_kernel

        base, W, head_w, head_b = maps
        B, H = base.shape[:2]
        history = self._room(H)
        S = np.empty((B, H + 1, state.shape[1]), np.float32)
        A = np.empty((B, H, head_w.shape[0]), np.float32)
        R = np.empty((B, H + 1), np.float32)
        S[:, 0], R[:, 0] = _numpy(state), _numpy(rtg)
        window = WindowMaps(_numpy(base), _numpy(W), _numpy(head_w), _numpy(head_b))
        rollout_kernel(
            self.step.address,
            self.params,
            COST_CODES[cost_norm],
            self.n_head,
            self.act,
            self.weights,
            self.K,
            self.V,
            history,
            start,
            window,
            _numpy(prev_action),
            S,
            A,
            R,
        )
        return torch.from_numpy(S), torch.from_numpy(A), torch.from_numpy(R)
