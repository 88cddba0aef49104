"""The compiled part of the fused decode (``ttompc.policy.fused``): numba functions over float32 arrays.

``rollout_kernel`` runs a whole H-step generation of ``RolloutContext.rollout`` (stacked layout) in one call:
per generated step the token embedding, the decoder layers over the KV cache (the new token's keys/values are
written into the free slots after the history, which the caller leaves unclaimed: the cache's ``length`` is never
touched here), the action head, the scenario's approximate dynamics (a numba ``cfunc``, called by its address:
``ttompc.scenarios.dynamics.call_step``) and the rtg update with the stage cost. ``extend_kernel`` runs the
trunk over T executed steps after the cached ones (the KV-cache extension of ``RolloutContext.advance``). Both embed
a step's token from its un-normalised inputs u = [goal, rtg, ctg, state, a_{k-1}] as ``TrajectoryGPT.embed_steps``
does (normalise, the stacked linear map, the timestep embedding: ``EmbedWeights``), so the token of a rollout's
first step is the one an extension by that step computes from the same inputs (``FusedDecoder`` claims it).

Matmuls go through ``np.dot`` (numba's BLAS binding, single-threaded under ``OMP_NUM_THREADS=1``): measured on the
2-core dev VM it is 2× (batch 1) to 3.5× (batch 40) faster than the best plain loops at these shapes. The rest is
loops compiled with ``reassoc``/``contract`` fast-math, so the attention's and LayerNorm's reductions vectorise
(no NaN/inf assumptions: a diverging plan stays visible). At batch 1 a generated step reads every trunk weight once
(0.6M parameters: 2.4 MB, 1.8M: 7.1 MB): the kernel is bound by the cache's bandwidth, not by arithmetic
(``bench/model_calls.py``).

The weights are a ``TrunkWeights``, the linear layers' weights transposed and contiguous (I, O): ``np.dot`` of a
batch with torch's (O, I) layout read transposed was measured up to 2.6× slower (batch 8, 384×128).

``KERNEL`` (``ttompc.compiled``) compiles this file's functions, cached on disk and keyed on its content. The first
use compiles both kernels and a scenario's dynamics step in about 12 s on the (loaded) 2-core dev VM, once per
machine, edit of this file and number of layers; a later process loads them from the cache in about 0.4 s.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ttompc.compiled import Kernel
from ttompc.scenarios import dynamics
from ttompc.scenarios.dynamics import call_step

COST_CODES = {"l1": 0, "l2": 1, "quad": 2}  # the stage cost c(u) of the rtg update
ACT_CODES = {"relu": 0, "gelu": 1, "silu": 2}  # the MLP activation (gelu: torch's exact erf form)
LN_EPS = 1e-5  # torch's LayerNorm default, what ``Decoder`` runs
# dynamics.py: ``call_step`` is compiled into the kernel
KERNEL = Kernel("the fused decode kernel", [Path(__file__), Path(dynamics.__file__)], fastmath={"reassoc", "contract"})
jit = KERNEL.jit


class LayerWeights(NamedTuple):
    """One decoder block: LayerNorm weights and biases (C,), linear weights transposed (in, out) and biases (out,)."""

    ln1_w: np.ndarray
    ln1_b: np.ndarray
    qkv_wT: np.ndarray  # (C, 3C)
    qkv_b: np.ndarray
    proj_wT: np.ndarray  # (C, C)
    proj_b: np.ndarray
    ln2_w: np.ndarray
    ln2_b: np.ndarray
    fc_wT: np.ndarray  # (C, hidden)
    fc_b: np.ndarray
    out_wT: np.ndarray  # (hidden, C)
    out_b: np.ndarray


class TrunkWeights(NamedTuple):
    """The trunk: the embedding's and the final LayerNorm's weights and biases (C,), and the blocks in order."""

    embed_ln_w: np.ndarray
    embed_ln_b: np.ndarray
    final_ln_w: np.ndarray
    final_ln_b: np.ndarray
    layers: tuple[LayerWeights, ...]


class EmbedWeights(NamedTuple):
    """The stacked token embedding and the action head (float32): the token of step k with un-normalised inputs
    u = [goal (n), rtg, ctg, state (n), a_{k-1} (m)] is ((u − mu)/sd) @ in_wT + in_b + time[k] (``embed_steps``), and
    the un-normalised action of a final hidden state h is head_w @ h + head_b (the normalisation folded in)."""

    mu: np.ndarray  # (I,), I = 2n+2+m: the inputs' means ...
    sd: np.ndarray  # (I,) ... and σ + ε (``NormStats.mean_std``)
    in_wT: np.ndarray  # (I, C)
    in_b: np.ndarray  # (C,)
    time: np.ndarray  # (max_steps, C): the timestep embedding
    head_w: np.ndarray  # (m, C)
    head_b: np.ndarray  # (m,)


@jit
def _layer_norm(x: Any, w: Any, b: Any, out: Any) -> None:
    """out = LayerNorm(x) rowwise: x, out (R, C); w, b (C,)."""
    R, C = x.shape
    for i in range(R):
        mu = np.float32(0.0)
        for c in range(C):
            mu += x[i, c]
        mu /= C
        var = np.float32(0.0)
        for c in range(C):
            d = x[i, c] - mu
            var += d * d
        inv = np.float32(1.0) / np.sqrt(var / C + np.float32(LN_EPS))
        for c in range(C):
            out[i, c] = (x[i, c] - mu) * inv * w[c] + b[c]


@jit
def _affine(x: Any, wT: Any, b: Any, out: Any) -> None:
    """out = x @ wT + b: x (R, I), wT (I, O) (the weight transposed), b (O,), out (R, O)."""
    np.dot(x, wT, out)
    for i in range(out.shape[0]):
        for o in range(out.shape[1]):
            out[i, o] += b[o]


@jit
def _activate(u: Any, act: int) -> None:
    """The MLP activation in place on u (R, O): 0 relu, 1 gelu (erf), 2 silu."""
    for i in range(u.shape[0]):
        for o in range(u.shape[1]):
            z = u[i, o]
            if act == 0:
                u[i, o] = max(z, np.float32(0.0))
            elif act == 1:
                u[i, o] = np.float32(0.5) * z * (np.float32(1.0) + math.erf(z * np.float32(0.7071067811865476)))
            else:
                u[i, o] = z / (np.float32(1.0) + np.exp(-z))


@jit
def _attend(qkv: Any, K: Any, V: Any, pos: int, n_head: int, p: Any, y: Any) -> None:
    """One new token per row at absolute position ``pos``: write its keys/values into K, V (R, heads, capacity, hd)
    at ``pos`` and attend over positions 0..pos. qkv (R, 3C) the token's q, k, v; p (≥ pos+1,) scratch; y (R, C)."""
    R, C = y.shape
    hd = C // n_head
    scale = np.float32(1.0 / math.sqrt(hd))
    for r in range(R):
        for h in range(n_head):
            o = h * hd
            q, out = qkv[r, o : o + hd], y[r, o : o + hd]  # (hd,) views
            Kh, Vh = K[r, h], V[r, h]  # (capacity, hd)
            Kh[pos] = qkv[r, C + o : C + o + hd]
            Vh[pos] = qkv[r, 2 * C + o : 2 * C + o + hd]
            top = -np.inf
            for j in range(pos + 1):
                kj = Kh[j]
                s = np.float32(0.0)
                for d in range(hd):
                    s += q[d] * kj[d]
                p[j] = s * scale
                top = max(top, p[j])
            total = np.float32(0.0)
            for j in range(pos + 1):
                p[j] = np.exp(p[j] - top)
                total += p[j]
            out[:] = 0.0
            for j in range(pos + 1):
                w, vj = p[j] / total, Vh[j]
                for d in range(hd):
                    out[d] += w * vj[d]


@jit
def _trunk(
    x: Any, pos: int, n_head: int, act: int, weights: TrunkWeights, K: Any, V: Any, scratch: tuple, out: Any
) -> None:
    """The decoder over one new token per row at position ``pos``: embedded tokens x (R, C) -> final hidden states
    out (R, C) (x is overwritten: the residual stream). K, V (L, R, heads, capacity, hd); ``scratch`` = (h (R, C),
    qkv (R, 3C), y (R, C), u (R, hidden), p (capacity,))."""
    h, qkv, y, u, p = scratch
    _layer_norm(x, weights.embed_ln_w, weights.embed_ln_b, h)
    x[:] = h
    i = 0
    for w in weights.layers:
        _layer_norm(x, w.ln1_w, w.ln1_b, h)
        _affine(h, w.qkv_wT, w.qkv_b, qkv)
        _attend(qkv, K[i], V[i], pos, n_head, p, y)
        _affine(y, w.proj_wT, w.proj_b, h)
        x += h
        _layer_norm(x, w.ln2_w, w.ln2_b, h)
        _affine(h, w.fc_wT, w.fc_b, u)
        _activate(u, act)
        _affine(u, w.out_wT, w.out_b, h)
        x += h
        i += 1
    _layer_norm(x, weights.final_ln_w, weights.final_ln_b, out)


@jit
def _scratch(R: int, C: int, hidden: int, capacity: int) -> tuple:
    f = np.float32
    return (
        np.empty((R, C), f),
        np.empty((R, 3 * C), f),
        np.empty((R, C), f),
        np.empty((R, hidden), f),
        np.empty(capacity, f),
    )


@jit
def _embed(u: Any, k: int, embed: EmbedWeights, z: Any, x: Any) -> None:
    """The tokens x (R, C) of step k from un-normalised inputs u (R, I) (``EmbedWeights``); z (R, I) scratch."""
    for r in range(u.shape[0]):
        for i in range(u.shape[1]):
            z[r, i] = (u[r, i] - embed.mu[i]) / embed.sd[i]
    np.dot(z, embed.in_wT, x)
    for r in range(x.shape[0]):
        for c in range(x.shape[1]):
            x[r, c] += embed.in_b[c] + embed.time[k, c]


@jit
def rollout_kernel(
    step: int,
    params: Any,
    cost: int,
    n_head: int,
    act: int,
    weights: TrunkWeights,
    embed: EmbedWeights,
    K: Any,
    V: Any,
    history: int,
    t0: int,
    u0: Any,
    S: Any,
    A: Any,
    R: Any,
) -> None:
    """The H = A.shape[1] generated steps of a rollout from step t0 after ``history`` cached tokens.

    ``step``: the address of the dynamics' float32 cfunc, called as step(s, a, k, params[b], s_next); ``params``
    (B, P) its per-problem rows. ``cost``: ``COST_CODES``; ``act``: ``ACT_CODES``. K, V (L, B, heads, capacity, hd): the
    cache; positions history..history+H-1 are written, nothing before. In: u0 (B, I), the un-normalised inputs of
    step t0 (``EmbedWeights``; the goal and ctg are held over the window). Out: S (B, H+1, n), A (B, H, m) and
    R (B, H+1), the window's states, actions and rtg from u0's state and rtg on."""
    B, H, m = A.shape
    n, C = S.shape[2], embed.in_wT.shape[1]
    x = np.empty((B, C), np.float32)
    hid = np.empty((B, C), np.float32)
    scratch = _scratch(B, C, weights.layers[0].fc_wT.shape[1], K.shape[3])
    u, z = u0.copy(), np.empty_like(u0)
    for b in range(B):
        R[b, 0] = u[b, n]
        S[b, 0] = u[b, n + 2 : 2 * n + 2]
    for j in range(H):
        _embed(u, t0 + j, embed, z, x)
        _trunk(x, history + j, n_head, act, weights, K, V, scratch, hid)
        for b in range(B):
            c = np.float32(0.0)
            for i in range(m):
                a = embed.head_b[i]
                for d in range(C):
                    a += embed.head_w[i, d] * hid[b, d]
                A[b, j, i] = a
                u[b, 2 * n + 2 + i] = a
                c += abs(a) if cost == 0 else a * a
            call_step(step, S[b, j], A[b, j], t0 + j, params[b], S[b, j + 1])
            R[b, j + 1] = R[b, j] + (c if cost == 0 else np.sqrt(c) if cost == 1 else np.float32(0.5) * c)
            u[b, n] = R[b, j + 1]
            u[b, n + 2 : 2 * n + 2] = S[b, j + 1]


@jit
def extend_kernel(
    n_head: int, act: int, weights: TrunkWeights, embed: EmbedWeights, K: Any, V: Any, start: int, k0: int, U: Any
) -> None:
    """The trunk over the tokens of T executed steps k0..k0+T-1 after ``start`` cached tokens, in order (step i's
    token at position start+i sees positions 0..start+i), from their un-normalised inputs U (B, T, I): their
    keys/values are written at start..start+T-1. Arguments as ``rollout_kernel``'s."""
    B, T, _ = U.shape
    C = embed.in_wT.shape[1]
    x = np.empty((B, C), np.float32)
    hid = np.empty((B, C), np.float32)
    z = np.empty((B, U.shape[2]), np.float32)
    scratch = _scratch(B, C, weights.layers[0].fc_wT.shape[1], K.shape[3])
    for i in range(T):
        _embed(U[:, i], k0 + i, embed, z, x)
        _trunk(x, start + i, n_head, act, weights, K, V, scratch, hid)
