"""The compact-QP backend (PIQP) against the conic assembly (Clarabel) and the independent cvxpy model on the same
subproblems, for every scenario it serves; the structural masks it relies on; and which path ``piqp`` (``auto``
without the Riccati kernel) takes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import qp_subproblem, waypoint_subproblem

from ttompc.scenarios import Window, get_scenario
from ttompc.solvers import SCPOptions, SCPProblem, TerminalCost, solve_rel, solve_scp
from ttompc.solvers.backends import get_solver
from ttompc.solvers.backends.base import is_qp
from ttompc.solvers.backends.conic import AssembledSolver
from ttompc.solvers.backends.qp import PIQPSolver
from ttompc.solvers.naive import NaiveCvxpySolver
from ttompc.solvers.spec import SubproblemSpec

CASES = [
    ("freeflyer", Window(0, 100, 100), True, True),
    ("freeflyer", Window(0, 100, 100), False, True),
    ("freeflyer", Window(60, 40, 100), True, True),
    ("freeflyer", Window(0, 100, 100), False, False),  # reference formulation: hard rows, no slacks
    ("quadrotor", Window(0, 100, 100), True, True),
    ("quadrotor", Window(0, 100, 100), False, True),
    ("quadrotor", Window(50, 50, 100), True, False),
]


@pytest.mark.parametrize(("name", "window", "obstacles", "penalized"), CASES)
def test_qp_matches_conic_and_cvxpy(name, window, obstacles, penalized) -> None:
    sc, spec, data = qp_subproblem(name, 3, window, obstacles, penalized, delta=0.3)
    assert is_qp(spec)
    X, U, qp = PIQPSolver(spec).solve(data)
    _, Uc, conic = AssembledSolver(spec, ["clarabel"]).solve(data)
    assert qp.ok and conic.ok, (qp.status, conic.status)
    assert qp.objective == pytest.approx(conic.objective, rel=1e-6, abs=1e-8)
    assert sc.cost(U) == pytest.approx(sc.cost(Uc), rel=1e-5, abs=1e-8)
    # the conic assembly stores only masked entries too: the dense assembly of the same data agrees
    dense = dataclasses.replace(spec, model_masks=None, blocks=tuple(sig[:8] for sig in spec.blocks))
    _, _, conic_dense = AssembledSolver(dense, ["clarabel"]).solve(data)
    assert AssembledSolver(dense, ["clarabel"]).sub.nnz > AssembledSolver(spec, ["clarabel"]).sub.nnz
    assert conic.objective == pytest.approx(conic_dense.objective, rel=1e-7, abs=1e-9)
    # the QP solution is a solution of the subproblem: initial state, model dynamics on the rows without virtual
    # control, trust region
    np.testing.assert_allclose(X[0], data.x_start, atol=1e-9)
    m = data.model
    exact = np.setdiff1d(np.arange(6), spec.virtual_rows()) if spec.virtual_control else np.arange(6)
    pred = np.einsum("hij,hj->hi", m.A, X[:-1]) + np.einsum("hij,hj->hi", m.B, U) + m.c
    assert len(exact) >= 3
    np.testing.assert_allclose(X[1:, exact], pred[:, exact], atol=1e-7)
    assert np.max(np.abs(X[1:-1] - data.X_ref[1:-1])) <= data.delta + 1e-7
    if name == "freeflyer" and window.start == 0 and obstacles:  # and the independent per-timestep model
        _, _, naive = NaiveCvxpySolver(spec).solve(data)
        assert qp.objective == pytest.approx(naive.objective, rel=1e-5)


def test_in_place_updates_give_the_fresh_optimum() -> None:
    """One solver reused across different data (as inside SCP) gives the optimum of a freshly built one."""
    _, spec, d1 = qp_subproblem("freeflyer", 5, Window(0, 100, 100), True, True, delta=0.5)
    _, spec2, d2 = qp_subproblem("freeflyer", 8, Window(0, 100, 100), True, True, delta=0.1)
    assert spec == spec2
    reused = PIQPSolver(spec)
    reused.solve(d1)
    _, U_reused, a = reused.solve(d2)
    _, U_fresh, b = PIQPSolver(spec).solve(d2)
    assert a.objective == pytest.approx(b.objective, rel=1e-7)
    # the free-flyer's L1 fuel has optimal faces: two solves can stop at other points of one face, at equal fuel
    sc = get_scenario("freeflyer")
    assert sc.cost(U_reused) == pytest.approx(sc.cost(U_fresh), rel=1e-6)


def test_fallback_on_numerical_failure() -> None:
    _, spec, data = qp_subproblem("quadrotor", 2, Window(0, 100, 100), True, True, delta=0.3)
    solver = PIQPSolver(spec, fallback=lambda: AssembledSolver(spec, ["clarabel"]))
    solver.solve(data)
    solver.solver.settings.max_iter = 1  # PIQP now stops unsolved: the conic solver takes over
    X, _, sol = solver.solve(data)
    assert X is not None and sol.ok and "PIQP_MAX_ITER_REACHED -> Solved" in sol.status
    ref = AssembledSolver(spec, ["clarabel"]).solve(data)[2]
    assert sol.objective == pytest.approx(ref.objective, rel=1e-6)


@pytest.mark.parametrize("name", ["freeflyer", "quadrotor", "rpod"])
def test_structural_masks_cover_every_nonzero(name) -> None:
    """Sparse backends store only masked entries: a reference-dependent value outside its mask would be dropped."""
    sc = get_scenario(name)
    rng = np.random.default_rng(0)
    for _ in range(3):
        p = sc.sample(rng)
        w = Window.full(p)
        X = sc.initial_guess(p)[0] + rng.normal(scale=0.3, size=(101, 6))
        U = rng.normal(scale=0.01, size=(100, 3))
        model = sc.convex_model(p, w, X, U)
        for arr, mask in ((model.A, model.A_mask), (model.B, model.B_mask)):
            if mask is not None:
                assert not np.any(np.asarray(arr)[:, ~mask])
        for block in sc.constraints(p, w, X, U, obstacles=True):
            if block.Gx_mask is not None:
                assert not np.any(block.Gx[:, ~block.Gx_mask]), block.name
            if block.Gu_mask is not None:
                assert not np.any(block.Gu[:, ~block.Gu_mask]), block.name


def test_the_piqp_path_uses_the_qp_where_there_is_no_cone() -> None:
    ff = get_scenario("freeflyer")
    p = ff.sample(np.random.default_rng(1))
    rel = solve_rel(ff, p, backend="piqp")
    assert rel.success and all("PIQP" in h.solver_status for h in rel.history)
    # an MPC window's soft terminal term is a 2-norm: the conic chain takes it, with the ∞-norm trust region
    w = Window(0, 10, 100)
    res = solve_scp(
        SCPProblem(ff, p, w, TerminalCost(rel.X[10], 1.0)), rel.X[:11], rel.U[:10], SCPOptions(backend="piqp")
    )
    assert res.success and not any("PIQP" in h.solver_status for h in res.history)
    # RPOD's 2-norm cost needs cones: its auto chain is conic only
    rp = get_scenario("rpod")
    assert get_scenario("rpod").auto_backends == ("clarabel",)
    for backend in ("auto", "piqp"):
        assert not isinstance(get_solver(_rpod_spec(rp), backend, rp), PIQPSolver)


def _rpod_spec(rp) -> SubproblemSpec:
    p = rp.sample(np.random.default_rng(0))
    X, U = rp.initial_guess(p)
    blocks = rp.constraints(p, Window.full(p), X, U, obstacles=True)
    return SubproblemSpec(
        100,
        6,
        3,
        "l2",
        1.0,
        True,
        False,
        "l2",
        "hard",
        False,
        100.0,
        tuple(SubproblemSpec.block_signature(b) for b in blocks),
    )


def test_piqp_alone_rejects_cones() -> None:
    """``PIQPSolver`` built for a subproblem with cones (RPOD's 2-norm cost) says so; the ``piqp`` chain never builds
    one (its conic solvers take such subproblems, above)."""
    with pytest.raises(ValueError, match="QPs only"):
        PIQPSolver(_rpod_spec(get_scenario("rpod")))


@pytest.mark.parametrize("penalized", [True, False])
def test_equality_blocks_match_conic(penalized) -> None:
    """Waypoint-type equality rows (hard, or with e± slacks when penalised) give the conic assembly's optimum."""
    spec, data, wp = waypoint_subproblem(penalized)
    X, _, qp = PIQPSolver(spec).solve(data)
    _, _, conic = AssembledSolver(spec, ["clarabel"]).solve(data)
    assert qp.ok and conic.ok
    assert qp.objective == pytest.approx(conic.objective, rel=1e-6)
    if not penalized:
        np.testing.assert_allclose(X[40, :2], wp.h[0], atol=1e-7)
