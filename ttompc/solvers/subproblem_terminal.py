"""The terminal section of the conic assembly (``subproblem.AssembledSubproblem``), by ``SubproblemSpec.terminal``,
and the values its rows read from ``SubproblemData``:

* ``hard``: x_H = goal, with slacks at the exact L1 penalty in the penalised formulation;
* ``soft``: τ ≥ ‖W(x_H − x̄)‖₂ at cost τ, the paper's soft terminal term (W = diag(w));
* ``sampled``: τ − cᵀλ ≥ ‖W(x_H − Zλ)‖₂ at cost τ, with λ ≥ 0 and 1ᵀλ = 1 (K = ``SubproblemSpec.samples``
  variables λ): the sampled terminal set of LMPC, the end state measured from the convex hull of the samples Z
  (n, K) at their combined cost-to-go cᵀλ (``SubproblemData.terminal_samples``, ``terminal_sample_costs``). Z and c
  enter through the constraint matrix, not q, so they are data of one structure, refreshed per iteration like the
  target; at the optimum τ is the window's terminal part, ``sample_hull.hull_cost`` of its end state;
* ``value``: a cost-to-go model alone, which only the riccati backend takes (``SubproblemData.terminal_cost``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ttompc.solvers.subproblem import AssembledSubproblem, SubproblemData, _Group


def terminal_rows(
    sub: AssembledSubproblem, zero: _Group, nonneg: _Group, q_parts: list[tuple[np.ndarray, float]]
) -> np.ndarray:
    """Add the terminal section of ``sub.spec`` to ``sub`` (its variables, rows and linear costs; module doc).
    Returns the indices in z of the term's τ followed by λ ("sampled"), of τ ("soft"), or none ("hard")."""
    spec = sub.spec
    H, n = spec.H, spec.n
    if spec.terminal == "hard":
        r = zero.add_rows(n)
        sub._entries(zero, r, sub.ix[H], ("const", np.ones(n)))
        zero.b.append((r, ("goal", np.arange(n), 1.0)))
        if spec.penalized:
            sp_, sm_ = sub._var(n), sub._var(n)
            sub._entries(zero, r, sp_, ("const", -np.ones(n)))
            sub._entries(zero, r, sm_, ("const", np.ones(n)))
            sub._nonneg_vars(nonneg, np.concatenate([sp_, sm_]))
            q_parts.append((np.concatenate([sp_, sm_]), spec.penalty))
        return np.zeros(0, dtype=np.int64)
    if spec.terminal == "value":
        raise ValueError("the conic path takes no terminal cost-to-go model yet: use backend='auto' (riccati)")
    if spec.terminal not in ("soft", "sampled"):
        raise ValueError(f"unknown terminal mode {spec.terminal!r}")
    tau = sub._var(1)
    g = sub._soc(1 + n)
    sub._entries(g, np.array([0]), tau, ("const", -np.ones(1)))
    sub._entries(g, np.arange(1, n + 1), sub.ix[H], ("data", ("terminal_weights", np.arange(n), -1.0)))
    q_parts.append((tau, 1.0))
    if spec.terminal == "soft":
        g.b.append((np.arange(1, n + 1), ("weighted_target", np.arange(n), -1.0)))
        return tau
    K = spec.samples
    if K < 1:
        raise ValueError(f"a sampled terminal set needs samples >= 1, got {K}")
    lam = sub._var(K)
    sub._entries(g, np.zeros(K, dtype=int), lam, ("data", ("sample_costs", np.arange(K), 1.0)))  # τ − cᵀλ
    rows, cols = np.repeat(np.arange(1, n + 1), K), np.tile(lam, n)  # entry i·K + k: row 1 + i, λ_k
    sub._entries(g, rows, cols, ("data", ("weighted_samples", np.arange(n * K), 1.0)))  # − W Z λ
    r = zero.add_rows(1)  # 1ᵀλ = 1
    sub._entries(zero, r, lam, ("const", np.ones(K)))
    zero.b.append((r, ("simplex", np.zeros(1, dtype=int), 1.0)))
    sub._nonneg_vars(nonneg, lam)
    return np.concatenate([tau, lam])


def terminal_sources(data: SubproblemData) -> dict[str, np.ndarray]:
    """The values the terminal rows read (``AssembledSubproblem.update``): the weights and the weighted target of
    the soft term, and the sampled set's weighted samples (n·K, row-major: W Z) and costs where the data has them."""
    src: dict[str, np.ndarray] = {}
    w = data.terminal_weights
    if w is not None and data.terminal_target is not None:
        src["terminal_weights"] = w
        src["weighted_target"] = w * data.terminal_target
    if data.terminal_samples is not None and data.terminal_sample_costs is not None:
        if w is None:
            raise ValueError("a sampled terminal set needs terminal_weights")
        src["terminal_weights"] = w
        src["weighted_samples"] = (w[:, None] * np.asarray(data.terminal_samples).T).ravel()
        src["sample_costs"] = np.asarray(data.terminal_sample_costs, dtype=np.float64)
        src["simplex"] = np.ones(1)
    return src
