"""The fused decode (``RolloutContext(..., decoder="fused")``, ``MPCSettings.decoder``): a cached rollout's whole
H-step generation in one compiled call, and the KV-cache extension of ``advance`` in another, or in none.

The torch rollout of a small model is dispatch-bound (``bench/model_calls.py``: ~60 torch ops per generated step,
the matmul arithmetic 10–18% of the time). ``FusedDecoder`` runs the same computation in numba
(``ttompc.policy.fused_kernel``), float32 like the torch path: per generated step the token embedding from the
step's un-normalised inputs (``TrajectoryGPT.embed_steps``), the decoder layers over the cached history and the
generated tokens, the action head, the scenario's approximate dynamics (``BatchedModel.fused_step``) and the rtg
update with the stage cost. It reads and writes the KV cache the torch ``Decoder`` would (zero-copy numpy views of
``KVCache.k``/``v``): a rollout writes its tokens into the free slots after the history and leaves ``length`` alone
(what the torch path truncates back to), an extension writes its tokens and advances ``length``, so the torch and
fused decoders can take turns on one cache. The results equal the torch path's up to float rounding
(``tests/test_fused_decode.py``), not bitwise.

The first token a rollout from step t writes (position t, right after a complete history) is the token of step t
that the extension by step t computes: the same inputs (goal, rtg, ctg, state of step t and a_{t-1}; never a_t)
through the same embedding and trunk. So the extension by an executed step *claims* it (``FusedDecoder.extend``:
the cache's length advances over it, no compute) when the rollout's inputs equal the executed step's, compared
exactly; otherwise (no rollout at that step, other inputs) it computes the token. An MPC step (a rollout, then the
advance by the executed step) is one compiled call.

It runs the ``stacked`` layout with a relu, gelu or silu MLP, a float32 model on the CPU, with the KV cache, and a
scenario whose batched model has ``fused_step`` (the three built-in ones). Elsewhere ``decoder="fused"`` raises
``ValueError`` naming the reason, and ``decoder="auto"`` runs the torch path, with the reason in
``RolloutContext.fallback`` and a ``RuntimeWarning`` (``resolve_decoder``). The weights are copied into the kernel's
layout (``fused_kernel.TrunkWeights``, ``EmbedWeights``) when the decoder is built, with its context: the rule of
``RolloutContext``, that the model's weights do not change while a context lives (its KV cache holds keys and values
computed with them), makes watching them for changes unnecessary; a context built after an optimizer step or
``load_state_dict`` computes with the new weights. The value output is not part of the decode: it prices the
measured state before the rollout (``Planner.cost_to_go``, in numpy on the CPU: no torch call).

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
    from ttompc.policy.fused_kernel import EmbedWeights, TrunkWeights
    from ttompc.policy.stats import NormStats


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


def embed_weights(model: TrajectoryGPT, stats: NormStats) -> EmbedWeights:
    """The stacked embedding and action head of ``model`` with ``stats`` in the kernel's layout
    (``fused_kernel.EmbedWeights``, float32 copies)."""
    from ttompc.policy.fused_kernel import EmbedWeights

    keys = ("goals", "rtg", "ctg", "states", "actions")  # ``embed_steps``' order of the stacked inputs
    moments = [stats.mean_std(key, np.zeros(1)) for key in keys]
    mu, sd = (np.concatenate(parts).astype(np.float32) for parts in zip(*moments, strict=True))
    lin = model.embed_stacked
    mu_a, sd_a = stats.mean_std("actions", np.zeros(1))
    head = model.action_head
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    return EmbedWeights(
        mu,
        sd,
        f32(_numpy(lin.weight).T),
        f32(_numpy(lin.bias)) if lin.bias is not None else np.zeros(lin.out_features, np.float32),
        _numpy(model.embed_timestep.weight).copy(),
        f32(_numpy(head.weight) * sd_a[:, None]),
        f32(_numpy(head.bias) * sd_a + mu_a),
    )


class FusedDecoder:
    """The trunk over a ``KVCache`` and the rollout, in one numba call each: ``extend`` appends executed steps to
    the history (claiming a rollout's first token where it is theirs, module doc), ``rollout`` generates a window.
    Both take a step's un-normalised inputs u = [goal, rtg, ctg, state, a_{k-1}] (``fused_kernel.EmbedWeights``).

    ``dynamics`` is the context's batched model (B problems, the cache's batch); its ``fused_step`` is read once,
    the model's weights copied once (``trunk_weights``, ``embed_weights``)."""

    def __init__(self, model: TrajectoryGPT, stats: NormStats, cache: KVCache, dynamics: BatchedModel) -> None:
        from ttompc.policy.fused_kernel import ACT_CODES

        self.model, self.cache = model, cache
        cfg = model.cfg
        self.n_head, self.act = cfg.n_head, ACT_CODES[cfg.activation]
        self.weights, self.embed = trunk_weights(model), embed_weights(model, stats)
        self.K, self.V = cache.k.numpy(), cache.v.numpy()  # (L, B, heads, capacity, hd) views, written in place
        self.step, self.params = cast(Any, dynamics).fused_step()  # the cfunc and its rows (B, P)
        if self.params.shape[0] != self.K.shape[1] or self.params.dtype != np.float32:
            raise ValueError(f"fused_step params must be float32 (B={self.K.shape[1]}, P), got {self.params.shape}")
        # the last rollout's first token: (its position, its step's inputs (B, I)), until the cache moves on
        self._claim: tuple[int, np.ndarray] | None = None
        self.claimed = 0  # tokens claimed so far (module doc), for tests and benches

    def _room(self, tokens: int) -> int:
        start = self.cache.length
        if start + tokens > self.cache.capacity:
            raise ValueError(f"KV cache overflow: {start + tokens} tokens > capacity {self.cache.capacity}")
        return start

    def extend(self, inputs: np.ndarray, k0: int) -> None:
        """Append the tokens of the executed steps k0..k0+T-1 from their un-normalised inputs (B, T, I) float32 after
        the cached ones (the cache length advances by T), as ``Decoder.__call__`` of their ``embed_steps`` tokens.
        The first one is claimed, not computed, where the last rollout wrote it from equal inputs (module doc)."""
        from ttompc.policy.fused_kernel import extend_kernel

        start = self._room(inputs.shape[1])
        claim, self._claim = self._claim, None
        if claim is not None and claim[0] == start and np.array_equal(claim[1], inputs[:, 0]):
            self.cache.length = start = start + 1
            self.claimed += 1
            inputs, k0 = inputs[:, 1:], k0 + 1
        if inputs.shape[1]:
            extend_kernel(self.n_head, self.act, self.weights, self.embed, self.K, self.V, start, k0, inputs)
            self.cache.length = start + inputs.shape[1]

    def rollout(self, u0: np.ndarray, t0: int, horizon: int, cost_norm: CostNorm) -> tuple[Tensor, Tensor, Tensor]:
        """The ``horizon`` steps from step ``t0`` after the cached history (whose length is left as it is; its free
        slots are scratch, the first of them kept for a claim). ``u0`` (B, I) float32: the un-normalised inputs of
        step t0 (the goal and ctg held over the window). -> states (B, H+1, n), actions (B, H, m), rtg (B, H+1)."""
        from ttompc.policy.fused_kernel import COST_CODES, rollout_kernel

        history = self._room(horizon)
        B, n, m = u0.shape[0], self.model.cfg.state_dim, self.model.cfg.control_dim
        S = np.empty((B, horizon + 1, n), np.float32)
        A = np.empty((B, horizon, m), np.float32)
        R = np.empty((B, horizon + 1), np.float32)
        rollout_kernel(
            self.step.address,
            self.params,
            COST_CODES[cost_norm],
            self.n_head,
            self.act,
            self.weights,
            self.embed,
            self.K,
            self.V,
            history,
            t0,
            u0,
            S,
            A,
            R,
        )
        self._claim = (history, u0.copy())
        return torch.from_numpy(S), torch.from_numpy(A), torch.from_numpy(R)
