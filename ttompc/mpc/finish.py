"""The finish cost: what a window that stops before N pays for the state it leaves behind (issue 35, a departure).

The paper's terminal term ‖x_{t+H} − x̄‖ says where a window should end, not what finishing from there costs. The
finish cost prices the rest of the episode: reaching the goal from x = x_{t+H} in the T = N − t − H steps left,
without keep-out zones, on the dynamics linearised along the straight line from x to the goal
(``Scenario.convex_model``)::

    x_N = Φ x + Σ_k G_k u_k + d,      G_k = A_{T−1} ⋯ A_{k+1} B_k,      W = Σ_k G_k G_kᵀ   (controllability Gramian)

The least control energy that meets x_N = goal is ½ rᵀ W⁻¹ r with r = goal − d − Φ x, a quadratic in x. So:

* quadratic stage cost (the quadrotor, ½‖u‖²): the finish cost is exactly w·½ rᵀ W⁻¹ r (``squared``), the cost of
  the optimal unconstrained finish;
* norm stage costs (free-flyer L1, RPOD L2): the least-fuel finish is a linear programme (a cone programme) with no
  closed form, positively homogeneous in r. Its price is the norm c·(rᵀ W⁻¹ r)^{1/2}, fitted at the warm start's
  last state x̂: c makes it equal there to the fuel Σ_k c(u*_k) of the least-energy finish u*_k = G_kᵀ W⁻¹ r(x̂), a
  feasible finish. Measured against the exact linear programme (``tests/test_finish.py``), that fuel is 1.0–1.5×
  the least fuel; the bare norm (c = 1, a lower bound: Σ c(u_k) ≥ ‖u‖₂ ≥ (rᵀ W⁻¹ r)^{1/2}) is 3–80× below it.

w is the window's stage-cost weight times ``MPCSettings.finish``. W is regularised by ``RIDGE``·tr(W)/n in the
scaled state units (``state_scale``), for a well-defined inverse only. With fewer than ⌈n/m⌉ + 1 steps left (about
the controllability index) exact finishing is priced absurdly high, while the loop's soft end term prices a miss
linearly: such windows get no finish cost (``finish_cost`` returns None).
"""

from __future__ import annotations

import numpy as np

from ttompc.scenarios.base import Problem, Scenario, Window
from ttompc.solvers.results import FinishCost

RIDGE = 1e-9


def min_tail(scenario: Scenario) -> int:
    """The fewest steps left after a window for it to get a finish cost: ⌈n/m⌉ + 1."""
    return -(-scenario.state_dim // scenario.control_dim) + 1


def finish_cost(
    scenario: Scenario, problem: Problem, window: Window, x: np.ndarray, weight: float
) -> FinishCost | None:
    """The finish cost of a window that stops before N (module doc), linearised along the straight line from ``x``
    (the warm start's last state) to the goal; ``weight`` = the stage-cost weight times ``MPCSettings.finish``. None
    when fewer steps are left than ``min_tail``."""
    if window.reaches_end:
        raise ValueError(f"window {window} reaches the end: nothing is left to finish")
    N = problem.n_steps
    if N - window.stop < min_tail(scenario):
        return None
    tail = Window(window.stop, N - window.stop, N)
    X_ref, U_ref = scenario.initial_guess(problem, tail, x)
    model = scenario.convex_model(problem, tail, X_ref, U_ref)
    n = scenario.state_dim
    d = np.zeros(n)
    M = np.eye(n)  # A_{T−1} ⋯ A_{k+1}, built backwards
    G = np.zeros((tail.length, n, scenario.control_dim))
    for k in range(tail.length - 1, -1, -1):
        G[k] = M @ model.B[k]
        d += M @ model.c[k]
        M = M @ model.A[k]
    Phi = M
    S = scenario.state_units()  # conditioning only: rᵀ W⁻¹ r does not depend on the units
    Gs = G / S[None, :, None]
    Ws = np.einsum("kim,kjm->ij", Gs, Gs)  # S⁻¹ W S⁻¹
    Ws += RIDGE * np.trace(Ws) / n * np.eye(n)
    Ws_inv = np.linalg.inv(Ws)
    R = np.linalg.cholesky(Ws_inv).T  # W_s⁻¹ = Rᵀ R
    L0, l0 = R @ (Phi / S[:, None]), R @ ((problem.goal - d) / S)  # ‖L0 x − l0‖² = rᵀ W⁻¹ r
    if scenario.cost_norm == "quad":
        k = np.sqrt(weight / 2)
        return FinishCost(L=k * L0, l=k * l0, squared=True)
    r_s = (problem.goal - d - Phi @ x) / S
    bound = float(np.linalg.norm(R @ r_s))
    u_star = np.einsum("kim,i->km", Gs, Ws_inv @ r_s)  # the least-energy finish from x
    c = scenario.cost(u_star) / bound if bound > 0 else 1.0
    return FinishCost(L=weight * c * L0, l=weight * c * l0, squared=False)
