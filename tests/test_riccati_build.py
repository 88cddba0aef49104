"""The Riccati backend's compiled per-iteration path (``riccati_build``) against its NumPy reference
(``RiccatiSolver.compiled = False``): the same stage QPs entry for entry (constraints dropped where the reference drops
them), the same objective to rounding, and the same REL + SCP solves, statuses and iterates, on every scenario."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import qp_subproblem, waypoint_subproblem

from ttompc.scenarios import Window, get_scenario
from ttompc.solvers import solve_problem
from ttompc.solvers.backends.riccati import RiccatiSolver, StageQP
from ttompc.solvers.backends.riccati_build import objective
from ttompc.solvers.backends.riccati_qp import StageQPData

CASES = [
    ("freeflyer", Window(0, 100, 100), True),
    ("freeflyer", Window(0, 100, 100), False),
    ("freeflyer", Window(60, 40, 100), True),
    ("quadrotor", Window(0, 100, 100), True),
    ("quadrotor", Window(30, 70, 100), True),
]


def _assert_same_qp(a: StageQPData, b: StageQPData) -> None:
    """Every array of the two stage QPs equal to the bit, of the same dtype, and C-contiguous (what the kernel's
    entry point reads without checking)."""
    for part in ("dynamics", "cost", "boxes", "rows", "cone"):
        for field, x, y in zip(getattr(a, part)._fields, getattr(a, part), getattr(b, part), strict=True):
            assert x.shape == y.shape and x.dtype == y.dtype, (part, field, x.shape, y.shape, x.dtype, y.dtype)
            assert np.array_equal(x, y), (part, field, np.max(np.abs(x - y)))
            assert x.flags.c_contiguous, (part, field)


@pytest.mark.parametrize(("name", "window", "obstacles"), CASES)
def test_compiled_build_is_the_reference_stage_qp(name, window, obstacles) -> None:
    _, spec, data = qp_subproblem(name, 3, window, obstacles, True, delta=0.3)
    stage = StageQP(spec)
    compiled = stage.build(data, compiled=True)
    _assert_same_qp(compiled, stage.build(data, compiled=False))
    assert len(compiled.rows.d) > 0  # the case has general rows, not only boxes


def test_penalised_equality_rows_are_the_reference() -> None:
    """Two-sided rows (a waypoint-type equality block: lower = upper) in both paths."""
    spec, data, _ = waypoint_subproblem(penalized=True)
    stage = StageQP(spec)
    _assert_same_qp(stage.build(data, compiled=True), stage.build(data, compiled=False))


def test_dropped_constraints_are_the_reference() -> None:
    """A box row whose coefficient is 0, rows with an infinite bound, a general row of zero coefficients (norm read
    as 1): the compiled path drops and keeps what the reference does."""
    _, spec, data = qp_subproblem("freeflyer", 4, Window(0, 100, 100), True, True, delta=0.3)
    stage = StageQP(spec)
    blocks = []
    for b, block in zip(stage.blocks, data.blocks, strict=True):
        Gx, h = block.Gx.copy(), block.h.astype(np.float64)
        live = np.argwhere(b.live & (b.single if b.single.any() else ~b.single)[None, :])
        (k1, r1), (k2, r2) = live[3], live[7]
        Gx[k1, r1] = 0.0
        if block.Gu is not None:
            block = dataclasses.replace(block, Gu=block.Gu.copy())
            block.Gu[k1, r1] = 0.0
        h[k2, r2] = np.inf
        blocks.append(dataclasses.replace(block, Gx=Gx, h=h))
    edited = dataclasses.replace(data, blocks=blocks)
    before = stage.build(data, compiled=False)
    after = stage.build(edited, compiled=True)
    _assert_same_qp(after, stage.build(edited, compiled=False))
    dropped = len(before.boxes.d) + len(before.rows.d) - len(after.boxes.d) - len(after.rows.d)
    assert dropped >= 2  # the infinite bounds and the zero box coefficients at least


@pytest.mark.parametrize("name", ["freeflyer", "quadrotor"])
def test_window_with_terminal_cone_and_cost_model(name) -> None:
    """An MPC window (soft terminal cone, a quadratic cost-to-go model): the same stage QP and the same objective."""
    from ttompc.solvers.spec import QuadraticTerminalCost

    sc, spec, data = qp_subproblem(name, 5, Window(20, 10, 100), True, True, delta=0.3)
    spec = dataclasses.replace(spec, end_form="soft", tr_states=tuple(range(1, 11)))
    n, rng = sc.state_dim, np.random.default_rng(2)
    M = rng.normal(size=(n, n))
    model = QuadraticTerminalCost(hessian=M @ M.T, gradient=rng.normal(size=n), center=data.X_ref[-1])
    data = dataclasses.replace(
        data, terminal_target=data.X_ref[-1] + 0.1, terminal_weights=np.linspace(1.0, 4.0, n), terminal_cost=model
    )
    stage = StageQP(spec)
    qp = stage.build(data, compiled=True)
    _assert_same_qp(qp, stage.build(data, compiled=False))
    y = rng.normal(size=(spec.H + 1, n + stage.nu))
    assert stage.objective(y, qp, data, compiled=True) == pytest.approx(
        stage.objective(y, qp, data, compiled=False), rel=1e-12
    )


@pytest.mark.parametrize(("name", "window", "obstacles"), CASES[:4])
def test_objective_is_the_reference(name, window, obstacles) -> None:
    """At a point that violates constraints (their penalties count) and at the kernel's solution."""
    _, spec, data = qp_subproblem(name, 3, window, obstacles, True, delta=0.3)
    stage = StageQP(spec)
    qp = stage.build(data)
    y = np.random.default_rng(0).normal(size=(spec.H + 1, spec.n + stage.nu))
    assert objective(qp, y) == pytest.approx(qp.objective(y), rel=1e-12)
    assert qp.objective(y) > qp.objective(np.zeros_like(y))  # the point is penalised: the test can fail
    _, _, sol = RiccatiSolver(spec).solve(data)
    assert sol.ok


@pytest.mark.parametrize("name", ["freeflyer", "quadrotor", "rpod"])  # (conftest adds a "toy" without SCP)
def test_solves_are_the_references(name, monkeypatch) -> None:
    """REL + SCP with the compiled path and the reference path: the same statuses, subproblem counts and solver
    statuses, and iterates equal to the bit (the same arithmetic in the same order)."""
    sc = get_scenario(name)
    results = {}
    for compiled in (False, True):
        monkeypatch.setattr(RiccatiSolver, "compiled", compiled)
        results[compiled] = [solve_problem(sc, sc.sample(np.random.default_rng(seed))) for seed in (0, 1)]
    for ref, comp in zip(results[False], results[True], strict=True):
        for a, b in zip(ref, comp, strict=True):
            assert (a is None) == (b is None)
            if a is None or b is None:
                continue
            assert (a.status, a.iterations, a.best_iteration) == (b.status, b.iterations, b.best_iteration)
            assert [h.solver_status for h in a.history] == [h.solver_status for h in b.history]
            np.testing.assert_array_equal(a.X, b.X)
            np.testing.assert_array_equal(a.U, b.U)
