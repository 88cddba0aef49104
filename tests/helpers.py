"""Builders shared by several test modules (fixtures stay in conftest.py; this module is importable by name)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from ttompc.data.config import GenerateConfig, SplitConfig
from ttompc.policy.stats import NormStats
from ttompc.scenarios import Window, get_scenario
from ttompc.solvers import solve_rel
from ttompc.solvers.spec import SubproblemData, SubproblemSpec

if TYPE_CHECKING:
    from ttompc.policy import Planner
    from ttompc.scenarios import Problem, Scenario

# what shrinks `ttompc train` (recipes/freeflyer/tiny.yaml) to a run of seconds: one thin layer, batches of 4
TINY_TRAIN = ("model.n_embd=32", "model.n_layer=1", "model.n_head=2", "data.batch_size=4")


def toy_stats(seed: int = 0) -> NormStats:
    """Non-trivial statistics so that a missing (de)normalisation changes results."""
    rng = np.random.default_rng(seed)
    mean = {
        "states": rng.normal(size=6),
        "actions": rng.normal(size=3) * 0.1,
        "goals": rng.normal(size=6),
        "rtg": np.array([-3.0]),
        "ctg": np.array([0.5]),
    }
    std = {
        "states": rng.uniform(0.5, 2.0, 6),
        "actions": rng.uniform(0.1, 0.5, 3),
        "goals": rng.uniform(0.5, 2, 6),
        "rtg": np.array([2.0]),
        "ctg": np.array([1.0]),
    }
    return NormStats(mean, std)


def tiny_toy_planner(seed: int = 0) -> Planner:
    """A real (randomly initialised) planner on the "toy" scenario registered by conftest.py."""
    import torch

    from ttompc.policy import ModelConfig, Planner, TrajectoryGPT

    torch.manual_seed(seed)
    cfg = ModelConfig(n_embd=32, n_layer=2, n_head=2, max_steps=12, dropout=0.0)
    return Planner(TrajectoryGPT(cfg).eval(), get_scenario("toy"), toy_stats(seed))


def tiny_dataset(
    out: Path,
    scenario: str,
    problems: int,
    splits: tuple[float, float, float],
    *,
    shard_size: int,
    seed: int = 0,
    workers: int = 1,
    solver: str | None = None,
) -> dict[str, Any]:
    """Generate an open-loop set of ``problems`` problems of ``scenario`` into ``out``, split (train, val, test) as
    ``splits`` says, as the tests that train on or read a small dataset do: no data card, no progress bar, the
    default solver unless ``solver`` names one (``data_fakes.SOLVER``: instant fake solves). Returns its manifest."""
    from ttompc.data.generate import generate

    extra = {} if solver is None else {"solver": solver}
    cfg = GenerateConfig(
        scenario=scenario,
        problems=problems,
        out=str(out),
        shard_size=shard_size,
        workers=workers,
        seed=seed,
        splits=SplitConfig(*splits),
        card_dir=None,
        **extra,
    )
    manifest = generate(cfg, progress=False)
    assert manifest is not None
    return manifest


def qp_subproblem(name: str, seed: int, window: Window, obstacles: bool, penalized: bool, delta: float):
    """(scenario, spec, data) of a subproblem linearised about a perturbed REL solution (so that linearisations,
    slacks and the trust region all matter), with the structure the engine would build."""
    sc = get_scenario(name)
    p = sc.sample(np.random.default_rng(seed))
    rel = solve_rel(sc, p, backend="clarabel")
    rng = np.random.default_rng(seed + 100)
    X = rel.X[window.start : window.stop + 1] + rng.normal(scale=0.02, size=(window.length + 1, sc.state_dim))
    U = rel.U[window.start : window.stop]
    X[0] = rel.X[window.start]
    model = sc.convex_model(p, window, X, U)
    blocks = sc.constraints(p, window, X, U, obstacles=obstacles)
    spec = SubproblemSpec(
        H=window.length,
        n=sc.state_dim,
        m=sc.control_dim,
        cost_norm=sc.cost_norm,
        fuel_weight=1.0,
        penalized=penalized,
        virtual_control=penalized and not sc.exact_linear_dynamics,
        vc_rows=tuple(sc.approximate_rows),
        trust="linf",
        end_form="hard",
        soft_equalities=False,
        penalty=sc.scp.penalty,
        blocks=tuple(SubproblemSpec.block_signature(b) for b in blocks),
        tr_states=tuple(range(1, window.length)),
        state_scale=sc.state_scale,
        control_scale=sc.control_scale,
        model_masks=SubproblemSpec.model_signature(model),
    )
    data = SubproblemData(X[0], model, blocks, X, delta, p.goal, None, None)
    return sc, spec, data


def waypoint_subproblem(penalized: bool):
    """(spec, data, block) of a free-flyer subproblem with a waypoint-type equality block (x, y at step 40) added."""
    import dataclasses

    from ttompc.scenarios import BlockKind, ConstraintBlock

    _, spec, data = qp_subproblem("freeflyer", 4, Window(0, 100, 100), True, penalized, delta=0.5)
    Gx = np.zeros((1, 2, 6))
    Gx[0, 0, 0] = Gx[0, 1, 1] = 1.0
    wp = ConstraintBlock("wp", BlockKind.EQ, np.array([40]), Gx, None, data.X_ref[40:41, :2] + 0.02)
    data = dataclasses.replace(data, blocks=[*data.blocks, wp])
    spec = dataclasses.replace(spec, blocks=(*spec.blocks, SubproblemSpec.block_signature(wp)))
    return spec, data, wp


def assert_rtg_ctg_by_hand(sc: Scenario, problem: Problem, row: dict, rtol: float) -> None:
    """A row's rtg and ctg against arithmetic independent of the functions that wrote them: rtg_0 = −J (the solver's
    recorded cost and the scenario's sum over the actions), each rtg step up by that step's stage cost, the last one
    the last control's; ctg_t the keep-out violations of x_t..x_{N−1}, counted state by state."""
    stage = sc.stage_cost(np.asarray(row["actions"], dtype=np.float64))
    J = float(sc.cost(np.asarray(row["actions"], dtype=np.float64)))
    rtg = np.asarray(row["rtg"], dtype=np.float64)
    assert rtg[0] == pytest.approx(-J, rel=rtol) and rtg[0] == pytest.approx(-float(row["cost"]), rel=rtol)
    np.testing.assert_allclose(np.diff(rtg), stage[:-1], rtol=0, atol=rtol * max(1.0, J))
    assert rtg[-1] == pytest.approx(-stage[-1], abs=rtol * max(1.0, J))
    X = np.asarray(row["states_opt"])
    violating = [int(np.sum(sc.violations(problem, X[t : t + 1]))) for t in range(sc.n_steps)]
    assert [int(c) for c in row["ctg"]] == [sum(violating[t:]) for t in range(sc.n_steps)]
