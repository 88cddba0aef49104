"""RPOD physics (paper §V-A): ROE/RTN maps, the STM and the control matrix against independent computations
(numerically integrated two-body motion, secular J2 element rates, finite differences of impulses), sampling, and
the REL/SCP solution's docking constraints."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ttompc.scenarios import InfeasibleProblemError, Problem, Scenario, Window, get_scenario
from ttompc.scenarios.orbits import (
    ISS_OE,
    J2,
    MU_EARTH,
    R_EARTH,
    control_matrix,
    mean_motion,
    orbital_period,
    propagate_chief,
    roe_to_rtn_matrix,
    stm_j2,
)
from ttompc.scenarios.rpod import (
    CONE_COS,
    HORIZON_GRID,
    KOZ_SCALE,
    N_STEPS,
    WAYPOINT_STEP,
    docking_geometry,
    make_problem,
    orbit_matrices,
)
from ttompc.solvers.scp import SCPResult, solve_problem

# ---------------------------------------------------------------------------------------- independent orbit tools


def oe_to_rv(oe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Keplerian elements [a, e, i, Ω, ω, M] -> ECI position/velocity (Kepler's equation by Newton iteration)."""
    a, e, i, raan, w, M = oe
    E = M
    for _ in range(50):
        E -= (E - e * np.sin(E) - M) / (1 - e * np.cos(E))
    nu = 2 * np.arctan2(np.sqrt(1 + e) * np.sin(E / 2), np.sqrt(1 - e) * np.cos(E / 2))
    p = a * (1 - e**2)
    r = p / (1 + e * np.cos(nu))
    r_pf = r * np.array([np.cos(nu), np.sin(nu), 0.0])
    v_pf = np.sqrt(MU_EARTH / p) * np.array([-np.sin(nu), e + np.cos(nu), 0.0])
    cO, sO, ci, si, cw, sw = np.cos(raan), np.sin(raan), np.cos(i), np.sin(i), np.cos(w), np.sin(w)
    R = np.array(
        [
            [cO * cw - sO * sw * ci, -cO * sw - sO * cw * ci, sO * si],
            [sO * cw + cO * sw * ci, -sO * sw + cO * cw * ci, -cO * si],
            [sw * si, cw * si, ci],
        ]
    )
    return R @ r_pf, R @ v_pf


def rv_to_qns(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """ECI state -> [a, e_x, e_y, i, Ω, u] (u = ω + M, robust for near-circular orbits)."""
    h = np.cross(r, v)
    a = 1.0 / (2.0 / np.linalg.norm(r) - v @ v / MU_EARTH)
    i = np.arccos(h[2] / np.linalg.norm(h))
    raan = np.arctan2(h[0], -h[1])
    n_hat = np.array([np.cos(raan), np.sin(raan), 0.0])
    m_hat = np.cross(h / np.linalg.norm(h), n_hat)
    e_vec = np.cross(v, h) / MU_EARTH - r / np.linalg.norm(r)
    ex, ey = e_vec @ n_hat, e_vec @ m_hat
    e, w = np.hypot(ex, ey), np.arctan2(ey, ex)
    theta = np.arctan2(r @ m_hat, r @ n_hat)
    nu = theta - w
    E = np.arctan2(np.sqrt(1 - e**2) * np.sin(nu), e + np.cos(nu))
    return np.array([a, ex, ey, i, raan, w + E - e * np.sin(E)])


def wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def qns_roe(chief: np.ndarray, deputy: np.ndarray) -> np.ndarray:
    """Scaled quasi-nonsingular ROE of a deputy w.r.t. a chief, both as [a, e_x, e_y, i, Ω, u]."""
    a = chief[0]
    dO = wrap(deputy[4] - chief[4])
    return a * np.array(
        [
            (deputy[0] - a) / a,
            wrap(deputy[5] - chief[5]) + dO * np.cos(chief[3]),
            deputy[1] - chief[1],
            deputy[2] - chief[2],
            deputy[3] - chief[3],
            dO * np.sin(chief[3]),
        ]
    )


def deputy_oe(chief: np.ndarray, roe: np.ndarray) -> np.ndarray:
    """Invert ``qns_roe`` for a chief given as Keplerian elements: the deputy's Keplerian elements."""
    a, e, i, raan, w, M = chief
    d = roe / a
    ex, ey = e * np.cos(w) + d[2], e * np.sin(w) + d[3]
    raan_d = raan + d[5] / np.sin(i)
    u_d = w + M + d[1] - (raan_d - raan) * np.cos(i)
    w_d = np.arctan2(ey, ex)
    return np.array([a * (1 + d[0]), np.hypot(ex, ey), i + d[4], raan_d, w_d, u_d - w_d])


def rtn_state(rc: np.ndarray, vc: np.ndarray, rd: np.ndarray, vd: np.ndarray) -> np.ndarray:
    """Deputy position/velocity relative to the chief in the rotating RTN frame."""
    h = np.cross(rc, vc)
    R = rc / np.linalg.norm(rc)
    N = h / np.linalg.norm(h)
    C = np.stack([R, np.cross(N, R), N])
    rho = C @ (rd - rc)
    omega = np.array([0.0, 0.0, np.linalg.norm(h) / (rc @ rc)])
    return np.concatenate([rho, C @ (vd - vc) - np.cross(omega, rho)])


def two_body(_t: float, y: np.ndarray) -> np.ndarray:
    out = np.empty_like(y)
    for j in (0, 6):
        r = y[j : j + 3]
        out[j : j + 3] = y[j + 3 : j + 6]
        out[j + 3 : j + 6] = -MU_EARTH * r / np.linalg.norm(r) ** 3
    return out


# ----------------------------------------------------------------------------------------------------- tests


@pytest.mark.parametrize("ecc", [0.0, ISS_OE[1]])
def test_keplerian_stm_matches_integrated_two_body_motion(ecc: float) -> None:
    """J2 = 0: Ψ_k Φ(τ_k) s_0 must follow the RTN state of a deputy ~100 m away, both spacecraft integrated as
    nonlinear Keplerian orbits, over one orbit. Ψ is the near-circular map, so the ISS eccentricity adds an O(e·|s|)
    error (~0.1 m); e = 0 leaves only second-order terms (|s|²/a ~ mm)."""
    chief = ISS_OE.copy()
    chief[1] = ecc
    roe0 = np.array([3.0, -40.0, 20.0, 70.0, 10.0, 80.0])
    rc, vc = oe_to_rv(chief)
    rd, vd = oe_to_rv(deputy_oe(chief, roe0))
    period = float(orbital_period(chief[0]))
    t = np.linspace(0.0, period, 25)
    sol = solve_ivp(
        two_body, (0.0, period), np.concatenate([rc, vc, rd, vd]), method="DOP853", t_eval=t, rtol=1e-12, atol=1e-8
    )
    truth = np.array([rtn_state(y[:3], y[3:6], y[6:9], y[9:]) for y in sol.y.T])
    oe_t = propagate_chief(chief, t)
    model = np.einsum(
        "kij,kjl,l->ki", roe_to_rtn_matrix(oe_t), stm_j2(np.broadcast_to(chief, (len(t), 6)), t, j2=0.0), roe0
    )
    pos_err = np.abs(model[:, :3] - truth[:, :3]).max()
    vel_err = np.abs(model[:, 3:] - truth[:, 3:]).max()
    pos_tol, vel_tol = (0.02, 2e-5) if ecc == 0 else (0.3, 5e-4)
    assert np.abs(truth[:, :3]).max() > 50.0  # a genuine ~100 m relative orbit
    print(f"e={ecc}: max position error {pos_err:.2e} m, velocity error {vel_err:.2e} m/s")
    assert pos_err < pos_tol and vel_err < vel_tol, (pos_err, vel_err)


def test_j2_stm_is_the_jacobian_of_secular_j2_propagation() -> None:
    """Propagate chief and deputy mean elements with the secular J2 rates (Ω̇, ω̇, Ṁ) and compare the central
    finite-difference Jacobian of ROE(τ) w.r.t. ROE(0) with Φ(oe, τ) — an independent check of the transcription."""
    chief = ISS_OE.copy()
    chief[1] = 0.01  # exaggerate the eccentricity so the e-dependent entries matter
    tau = 2.5 * float(orbital_period(chief[0]))

    def secular(oe: np.ndarray) -> np.ndarray:
        a, e, i = oe[:3]
        eta = np.sqrt(1 - e**2)
        k = 0.75 * J2 * (R_EARTH / (a * eta**2)) ** 2 * mean_motion(a)
        rates = np.array(
            [
                0,
                0,
                0,
                -2 * k * np.cos(i),
                k * (5 * np.cos(i) ** 2 - 1),
                mean_motion(a) + k * eta * (3 * np.cos(i) ** 2 - 1),
            ]
        )
        return oe + rates * tau

    def roe_of(oe_c: np.ndarray, oe_d: np.ndarray) -> np.ndarray:
        def q(o: np.ndarray) -> np.ndarray:
            return np.array([o[0], o[1] * np.cos(o[4]), o[1] * np.sin(o[4]), o[2], o[3], o[4] + o[5]])

        return qns_roe(q(oe_c), q(oe_d))

    chief_f = secular(chief)
    J = np.zeros((6, 6))
    h = 10.0  # m (ROE are linear to ~1e-9 at this size)
    for j in range(6):
        dp, dm = np.zeros(6), np.zeros(6)
        dp[j], dm[j] = h, -h
        J[:, j] = roe_of(chief_f, secular(deputy_oe(chief, dp))) - roe_of(chief_f, secular(deputy_oe(chief, dm)))
        J[:, j] /= 2 * h
    phi = stm_j2(chief, tau)
    assert np.abs(phi - np.eye(6)).max() > 1e-3  # J2 terms are visible
    np.testing.assert_allclose(J, phi, rtol=0, atol=1e-7)  # smallest e-dependent entries are ~5e-5


def test_control_matrix_matches_finite_difference_of_impulses() -> None:
    """B(oe) vs the change of the osculating ROE when an RTN impulse is added to the chief's velocity (e = 0)."""
    chief = ISS_OE.copy()
    chief[1] = 0.0
    rc, vc = oe_to_rv(chief)
    C = np.stack([rc / np.linalg.norm(rc), np.cross(np.cross(rc, vc), rc), np.cross(rc, vc)])
    C /= np.linalg.norm(C, axis=1, keepdims=True)
    qc = rv_to_qns(rc, vc)
    dv = 1e-2  # m/s; round-off of the ECI -> element conversion dominates below this
    J = np.stack(
        [
            (qns_roe(qc, rv_to_qns(rc, vc + dv * C[j])) - qns_roe(qc, rv_to_qns(rc, vc - dv * C[j]))) / (2 * dv)
            for j in range(3)
        ],
        axis=1,
    )
    B = control_matrix(chief)
    np.testing.assert_allclose(J, B, rtol=0, atol=1e-3)  # entries are 68..1774 s


def test_roe_rtn_round_trip_and_target_fixed_point() -> None:
    sc = get_scenario("rpod")
    problem = sc.sample(np.random.default_rng(3))
    mats = orbit_matrices(problem)
    np.testing.assert_allclose(mats.psi @ mats.psi_inv, np.broadcast_to(np.eye(6), mats.psi.shape), atol=1e-9)
    X = np.random.default_rng(4).normal(scale=100.0, size=(N_STEPS + 1, 6))
    np.testing.assert_allclose(sc.from_model_states(problem, sc.to_model_states(problem, X)), X, atol=1e-8)
    # The docking target's ROE is the same at every epoch and a fixed point of every Φ_k, so x_N = goal is the
    # reference's "last impulse lands on the target" (s_{N-1} + B a_{N-1} = target).
    for sign in (-1, 1):
        target = docking_geometry(sign).target
        roe = mats.psi_inv @ target
        np.testing.assert_allclose(roe, np.broadcast_to(roe[0], roe.shape), atol=1e-9)
        np.testing.assert_allclose(mats.phi @ roe[0], np.broadcast_to(roe[0], (N_STEPS, 6)), atol=1e-9)
    x_prev = np.array([1.0, 60.0, 3.0, -2.0, 5.0, 4.0])
    u = np.linalg.lstsq(mats.B[-1], problem.goal - x_prev, rcond=None)[0]
    hit = x_prev + mats.B[-1] @ u
    np.testing.assert_allclose(sc.step(problem, N_STEPS - 1, x_prev, u), mats.phi[-1] @ hit, atol=1e-12)
    np.testing.assert_allclose(mats.phi[-1] @ problem.goal, problem.goal, atol=1e-9)


def test_sampling_reaches_every_grid_end_and_is_passively_safe() -> None:
    sc = get_scenario("rpod")
    rng = np.random.default_rng(0)
    problems = [sc.sample(rng) for _ in range(1500)]
    horizons = np.array([p.params["horizon_orbits"] for p in problems])
    assert horizons.max() == HORIZON_GRID[-1] and horizons.min() == HORIZON_GRID[0]
    da = np.array([p.x0[0] for p in problems])
    assert da.max() == 5.0 and da.min() == -5.0
    assert {p.params["dock_sign"] for p in problems} == {-1, 1}
    for p in problems[:100]:
        sc.validate(p)
        mats = orbit_matrices(p)
        np.testing.assert_allclose(
            mats.psi[N_STEPS] @ p.goal, docking_geometry(p.params["dock_sign"]).target, atol=1e-9
        )
        # passively safe: the free drift never enters the KOZ
        drift = [p.x0]
        for k in range(N_STEPS):
            drift.append(mats.phi[k] @ drift[-1])
        assert sc.violations(p, np.array(drift)).sum() == 0


def test_violations_only_before_the_waypoint() -> None:
    sc = get_scenario("rpod")
    problem = make_problem(np.array([0.0, 0.0, 0.0, 80.0, 0.0, 140.0]), 2.0, 1)
    inside = np.array([10.0, 20.0, -5.0, 0.0, 0.0, 0.0])
    S = np.tile(np.array([0.0, 300.0, 0.0, 0.0, 0.0, 0.0]), (N_STEPS + 1, 1))
    S[[5, 89, 90, 99]] = inside
    counts = sc.violations(problem, sc.from_model_states(problem, S))
    assert counts.tolist() == [int(k in (5, 89)) for k in range(N_STEPS + 1)]
    # windowed call: absolute index = start + row
    assert sc.violations(problem, sc.from_model_states(problem, S[85:95], start=85), start=85).tolist() == [
        int(k == 89) for k in range(85, 95)
    ]
    bad = make_problem(sc.from_model_states(problem, inside[None])[0], 2.0, 1)
    with pytest.raises(InfeasibleProblemError):
        sc.validate(bad)


def test_constraint_blocks_follow_the_window() -> None:
    sc = get_scenario("rpod")
    problem = sc.sample(np.random.default_rng(1))
    X, U = sc.initial_guess(problem)
    for start, length, names in [
        (0, 100, {"koz", "waypoint", "cone"}),
        (80, 15, {"koz", "waypoint", "cone"}),
        (90, 10, {"cone"}),
        (0, 50, {"koz"}),
        (89, 5, {"waypoint", "cone"}),
    ]:
        w = Window(start, length, N_STEPS)
        blocks = {
            b.name: b for b in sc.constraints(problem, w, X[start : w.stop + 1], U[start : w.stop], obstacles=True)
        }
        assert set(blocks) == names
        absolute = {n: (b.steps + start).tolist() for n, b in blocks.items()}
        if "koz" in absolute:
            assert absolute["koz"] == list(range(start + 1, min(WAYPOINT_STEP, w.stop + 1)))
        if "cone" in absolute:
            assert absolute["cone"] == list(range(max(WAYPOINT_STEP, start + 1), w.stop + 1))
        if "waypoint" in absolute:
            assert absolute["waypoint"] == [WAYPOINT_STEP]
        rel = {b.name for b in sc.constraints(problem, w, X[start : w.stop + 1], U[start : w.stop], obstacles=False)}
        assert rel == names - {"koz"}


def test_koz_linearisation_is_the_tangent_plane() -> None:
    """The KOZ row is the scaled ellipsoid's tangent plane at the radial projection of the reference: it passes
    through that projection and every point of the ellipsoid satisfies ≤ (violates) it."""
    sc = get_scenario("rpod")
    problem = sc.sample(np.random.default_rng(2))
    X, U = sc.initial_guess(problem)
    koz = next(b for b in sc.constraints(problem, Window.full(problem), X, U, obstacles=True) if b.name == "koz")
    psi = orbit_matrices(problem).psi
    rng = np.random.default_rng(0)
    for row, k in enumerate(koz.steps[:40]):
        r = psi[k, :3] @ X[k]
        proj = r / np.linalg.norm(r * KOZ_SCALE)
        x_proj = np.linalg.solve(psi[k], np.concatenate([proj, np.zeros(3)]))
        assert koz.Gx[row, 0] @ x_proj == pytest.approx(koz.h[row, 0], abs=1e-9)
        outside = np.linalg.norm(r * KOZ_SCALE) >= 1.0
        assert (koz.Gx[row, 0] @ X[k] <= koz.h[row, 0] + 1e-9) == outside
        # the half-space excludes the whole ellipsoid
        dirs = rng.normal(size=(50, 3))
        on = dirs / np.linalg.norm(dirs * KOZ_SCALE, axis=1, keepdims=True)
        x_on = np.linalg.solve(psi[k], np.concatenate([on, np.zeros((50, 3))], axis=1).T).T
        assert np.all(x_on @ koz.Gx[row, 0] >= koz.h[row, 0] - 1e-9)


def _check_docking(sc: Scenario, problem: Problem, res: SCPResult) -> None:
    geo = docking_geometry(problem.params["dock_sign"])
    S = sc.to_model_states(problem, res.X)
    assert sc.violations(problem, res.X).sum() == 0
    np.testing.assert_allclose(S[WAYPOINT_STEP], geo.waypoint, atol=1e-3)
    d = S[WAYPOINT_STEP:, :3] - geo.cone_vertex
    assert np.all(CONE_COS * np.linalg.norm(d, axis=1) <= d @ geo.cone_axis + 1e-4)
    np.testing.assert_allclose(S[-1], geo.target, atol=1e-3)
    np.testing.assert_allclose(sc.rollout(problem, res.U), res.X, atol=1e-3)


def test_rel_and_scp_dock_safely() -> None:
    sc = get_scenario("rpod")
    problem = sc.sample(np.random.default_rng(9))
    rel, scp = solve_problem(sc, problem, backend="clarabel")  # QOCO (the 'auto' default) is unreliable on RPOD
    assert rel.success and rel.iterations == 1
    assert sc.violations(problem, rel.X).sum() > 0  # the KOZ matters for this problem
    assert scp is not None and scp.success
    _check_docking(sc, problem, scp)
    assert rel.cost <= scp.cost + 1e-6
    assert sc.path_violation(problem, scp.X, scp.U, Window.full(problem)) <= sc.scp.feas_tol


@pytest.mark.parametrize("n_axes", [1, 3])
def test_plot_draws_the_rtn_projections(n_axes: int) -> None:
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sc = get_scenario("rpod")
    problem = sc.sample(np.random.default_rng(0))
    X, _ = sc.initial_guess(problem)
    fig, axes = plt.subplots(1, n_axes)
    sc.plot(axes, problem, {"guess": X})
    for ax in np.atleast_1d(axes):
        assert len(ax.lines) >= 4 and len(ax.patches) == 1  # cone edges, trajectory, markers; KOZ ellipse
    plt.close(fig)
