"""The free-flyer and quadrotor problems in CasADi ``Opti`` terms, shared by the NLP peers of
``bench/solver_speed.py`` (``ipopt_peer.py``, ``fatrop_peer.py``): the scenarios' own dynamics, bounds, keep-out
radii and costs, written over blocks of K steps (one column per step), so that IPOPT's whole-trajectory variables
(K = N) and fatrop's stage-wise ones (K = 1) are posed by the same expressions. Needs ``casadi`` (the ``peer``
extra).

Each function that adds constraints adds only constraints on the columns it is given, in a fixed order, so that a
caller controls the order of the rows (fatrop needs each stage's dynamics first). ``solve_timed`` solves a built
problem and collects what the benchmark reports."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ttompc.scenarios import freeflyer as ff
from ttompc.scenarios import quadrotor as qr

N_STEPS = 100  # both scenarios' horizon (ff.N_STEPS == qr.N_STEPS)
STATE_DIM = 6


@dataclass
class PeerResult:
    ok: bool
    X: np.ndarray  # (N+1, n)
    U: np.ndarray  # (N, m)
    iterations: int  # the NLP solver's iterations
    seconds: float


def control_variables(
    opti: Any, name: str, K: int, scale: np.ndarray | None = None
) -> tuple[Any, tuple[Any, ...], Any]:
    """New control variables for K steps: (U (3, K) expression, the decision variables, their cost). The free-flyer's
    L1 cost goes through U = U⁺ − U⁻ with U± ≥ 0 (``control_constraints`` adds the signs), cost Σ(U⁺ + U⁻); the
    quadrotor's is ½‖U‖². With ``scale`` (3,) the variables are in those units: U = diag(scale) · variables."""
    import casadi as ca

    def units(V: Any) -> Any:
        return V if scale is None else ca.diag(ca.DM(np.asarray(scale, dtype=np.float64))) @ V

    if name == "freeflyer":
        Up, Um = opti.variable(3, K), opti.variable(3, K)
        return units(Up - Um), (Up, Um), ca.sum1(ca.sum2(units(Up + Um)))
    V = opti.variable(3, K)
    return units(V), (V,), 0.5 * ca.sumsqr(units(V))


def set_control_guess(opti: Any, variables: tuple[Any, ...], U: np.ndarray, scale: np.ndarray | None = None) -> None:
    """Initial guess of ``control_variables``' variables from controls U (3, K): U± = max(±U, 0) for the split."""
    V = U if scale is None else U / np.asarray(scale, dtype=np.float64)[:, None]
    if len(variables) == 2:
        opti.set_initial(variables[0], np.maximum(V, 0))
        opti.set_initial(variables[1], np.maximum(-V, 0))
    else:
        opti.set_initial(variables[0], V)


def next_states(name: str, X: Any, U: Any) -> Any:
    """The scenario's discrete dynamics: states (6, K) and controls (3, K) -> the next states (6, K)."""
    import casadi as ca

    if name == "freeflyer":
        return ca.DM(ff.A_STEP) @ X + ca.DM(ff.A_STEP @ ff.B_IMP) @ U
    v = X[3:, :]
    speed = ca.sqrt(ca.sum1(v**2) + 1e-12)  # smooth at v = 0 (the drag is O(‖v‖²) there)
    drag = -(qr.DRAG / qr.MASS) * ca.repmat(speed, 3, 1) * v
    return X + qr.DT * ca.vertcat(v, U / qr.MASS + drag)


def control_constraints(opti: Any, name: str, X: Any, U: Any, variables: tuple[Any, ...]) -> None:
    """Constraints of steps 0..N−1 on states X (6, K) and controls U (3, K): the free-flyer's split signs and
    per-cluster thruster bound |Λ⁻¹R_BG(ψ)u| ≤ Δv_max, the quadrotor's control box."""
    import casadi as ca

    if name == "freeflyer":
        for part in variables:
            opti.subject_to(ca.vec(part) >= 0)
        c, s = ca.cos(X[2, :]), ca.sin(X[2, :])
        body = ca.vertcat(c * U[0, :] + s * U[1, :], -s * U[0, :] + c * U[1, :], U[2, :])
        opti.subject_to(opti.bounded(-ff.DV_MAX, ca.vec(ca.DM(ff.LAMBDA_INV) @ body), ff.DV_MAX))
    else:
        opti.subject_to(opti.bounded(-qr.U_MAX, ca.vec(U), qr.U_MAX))


def state_constraints(opti: Any, name: str, X: Any, obstacles: bool) -> None:
    """Constraints of steps 1..N on states X (6, K): the free-flyer's table box, and with ``obstacles`` the keep-out
    spheres (squared distance ≥ radius²)."""
    if name == "freeflyer":
        for d in range(2):
            opti.subject_to(opti.bounded(ff.TABLE[0][d], X[d, :], ff.TABLE[1][d]))
        centres, radii = ff.OBSTACLES, np.full(len(ff.OBSTACLES), ff.R_EFF)
    else:
        centres, radii = qr.OBSTACLES, qr.OBSTACLE_RADII
    if obstacles:
        for centre, r in zip(centres, radii, strict=True):
            d2 = sum((X[i, :] - centre[i]) ** 2 for i in range(len(centre)))
            opti.subject_to(d2 >= r**2)


def solve_timed(opti: Any, X: Any, U: Any) -> tuple[PeerResult, dict[str, Any]]:
    """Solve ``opti`` as set (parameters, initial guesses): the states X and controls U of the solution, or of the last
    iterate where the solver did not converge (``ok`` False), its iterations and wall time; and the solver's stats."""
    t0 = time.perf_counter()
    try:
        sol = opti.solve()
        ok, getter = True, sol.value
    except RuntimeError:  # no convergence; the debug values are the last iterate
        ok, getter = False, opti.debug.value
    seconds = time.perf_counter() - t0
    stats = opti.stats()
    X_value, U_value = np.asarray(getter(X)).T, np.asarray(getter(U)).T
    iterations = int(stats.get("iter_count", -1))
    return PeerResult(ok and bool(stats.get("success", False)), X_value, U_value, iterations, seconds), stats
