"""The compiled part of the fused decode (``ttompc.policy.fused``): numba functions over float32 arrays.

``rollout_kernel`` runs a whole H-step generation of ``RolloutContext.rollout`` (stacked layout) in one call:
per generated step the window embedding, the decoder layers over the KV cache (the new token's keys/values are
written into the free slots after the history, which the caller leaves unclaimed: the cache's ``length`` is never
touched here), the action head, the scenario's approximate dynamics (a numba ``cfunc``, called by its address:
``ttompc.scenarios.dynamics.call_step``) and the rtg update with the stage cost. ``extend_kernel`` runs the
trunk over T new tokens after the cached ones (the KV-cache extension of ``RolloutContext.advance``).

Matmuls go through ``np.dot`` (numba's BLAS binding, single-threaded under ``OMP_NUM_THREADS=1``): measured on the
2-core dev VM it is 2× (batch 1) to 3.5× (batch 40) faster than the best plain loops at these shapes. The rest is
loops compiled with ``reassoc``/``contract`` fast-math, so the attention's and LayerNorm's reductions vectorise
(no NaN/inf assumptions: a diverging plan stays visible).

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


class WindowMaps(NamedTuple):
    """A rollout window's embedding and action head (``RolloutContext._window_maps``): the tokens of step t0+j are
    base[:, j] + [rtg, state, a_prev] @ Wz, and the un-normalised action of a hidden state h is head_w @ h + head_b."""

    base: np.ndarray  # (B, H, C)
    Wz: np.ndarray  # (1+n+m, C)
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
def rollout_kernel(
    step: int,
    params: Any,
    cost: int,
    n_head: int,
    act: int,
    weights: TrunkWeights,
    K: Any,
    V: Any,
    history: int,
    t0: int,
    maps: WindowMaps,
    a_prev: Any,
    S: Any,
    A: Any,
    R: Any,
) -> None:
    """The H = A.shape[1] generated steps of a rollout from step t0 after ``history`` cached tokens.

    ``step``: the address of the dynamics' float32 cfunc, called as step(s, a, k, params[b], s_next); ``params``
    (B, P) its per-problem rows. ``cost``: ``COST_CODES``; ``act``: ``ACT_CODES``. K, V (L, B, heads, capacity, hd): the
    cache; positions history..history+H-1 are written, nothing before. In: a_prev (B, m) = a_{t0-1}, S[:, 0]
    (B, n) and R[:, 0] (B,). Out: S[:, 1:] (B, H, n), A (B, H, m), R[:, 1:]."""
    B, H, m = A.shape
    base, Wz, head_w, head_b = maps
    n, C = S.shape[2], Wz.shape[1]
    x = np.empty((B, C), np.float32)
    hid = np.empty((B, C), np.float32)
    scratch = _scratch(B, C, weights.layers[0].fc_wT.shape[1], K.shape[3])
    z = np.empty((B, 1 + n + m), np.float32)
    for b in range(B):
        z[b, 1 + n :] = a_prev[b]
    for j in range(H):
        for b in range(B):
            z[b, 0] = R[b, j]
            z[b, 1 : 1 + n] = S[b, j]
        np.dot(z, Wz, x)
        x += base[:, j]
        _trunk(x, history + j, n_head, act, weights, K, V, scratch, hid)
        for b in range(B):
            c = np.float32(0.0)
            for i in range(m):
                a = head_b[i]
                for d in range(C):
                    a += head_w[i, d] * hid[b, d]
                A[b, j, i] = a
                z[b, 1 + n + i] = a
                c += abs(a) if cost == 0 else a * a
            call_step(step, S[b, j], A[b, j], t0 + j, params[b], S[b, j + 1])
            R[b, j + 1] = R[b, j] + (c if cost == 0 else np.sqrt(c) if cost == 1 else np.float32(0.5) * c)


@jit
def extend_kernel(
    n_head: int, act: int, weights: TrunkWeights, K: Any, V: Any, start: int, tokens: Any, out: Any
) -> None:
    """The trunk over T new tokens (B, T, C) after ``start`` cached ones, in order (token i at position start+i
    sees positions 0..start+i): their keys/values are written at start..start+T-1 and out (B, T, C) gets their
    final hidden states. Arguments as ``rollout_kernel``'s."""
    B, T, C = tokens.shape
    x = np.empty((B, C), np.float32)
    hid = np.empty((B, C), np.float32)
    scratch = _scratch(B, C, weights.layers[0].fc_wT.shape[1], K.shape[3])
    for i in range(T):
        x[:] = tokens[:, i]
        _trunk(x, start + i, n_head, act, weights, K, V, scratch, hid)
        out[:, i] = hid
