"""The value output (a learned cost-to-go fed as rtg, ``rtg_mode=value``), its loss and masking, value-only training
on a frozen policy, and old bundles that keep the paper's ledger."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from test_training import ToyDataModule, tiny_config

from ttompc.config import ConfigError, to_container
from ttompc.data.schema import SOURCE_CODES
from ttompc.mpc.providers import RemainingOptimum
from ttompc.mpc.rtg import rtg_feed
from ttompc.mpc.tto import TTOProvider
from ttompc.policy import Planner
from ttompc.policy.config import ModelConfig
from ttompc.policy.gpt import TrajectoryGPT
from ttompc.policy.stats import NormStats
from ttompc.scenarios import get_scenario
from ttompc.scenarios.base import Window
from ttompc.solvers.scp import solve_problem
from ttompc.training.module import TrajectoryTransformerModule
from ttompc.training.run import load_source_weights, train

SCP, REL = SOURCE_CODES["scp"], SOURCE_CODES["rel"]


class SourcedToyData(ToyDataModule):
    """The toy batches with a ``source`` per row: every other row REL (no optimum's cost-to-go), the rest SCP."""

    def setup(self, stage: str | None = None) -> None:
        super().setup(stage)
        for ds in (self.train_set, self.val_set):
            n = len(ds)
            ds.items["source"] = torch.where(torch.arange(n) % 2 == 0, REL, SCP)


def _module(*overrides: str) -> tuple[TrajectoryTransformerModule, dict[str, torch.Tensor]]:
    dm = SourcedToyData(n=32, batch_size=16)
    dm.setup("fit")
    cfg = tiny_config(Path("unused"), "model.layout=stacked", "model.value_width=16", *overrides)
    assert dm.stats is not None
    module = TrajectoryTransformerModule(
        to_container(cfg.model), to_container(cfg.optim), "toy", "0.1", dm.stats.to_dict()
    )
    return module, next(iter(dm.train_dataloader()))


def test_value_loss_reads_only_valid_steps_of_rows_with_an_optimum() -> None:
    torch.manual_seed(0)
    module, batch = _module()
    base = module.value_loss(batch).item()
    assert base > 0
    rel = batch["source"] == REL
    assert rel.any() and (~rel).any()
    moved = dict(batch, rtg=batch["rtg"] + 5.0 * rel[:, None, None])  # REL rows' rtg: not a target
    assert module.value_loss(moved).item() == pytest.approx(base)
    padded = dict(batch, rtg=batch["rtg"] + 5.0 * (batch["mask"] == 0)[..., None])  # padded steps: not a target
    assert module.value_loss(padded).item() == pytest.approx(base)
    scp = dict(batch, rtg=batch["rtg"] + 5.0 * (~rel)[:, None, None])
    assert module.value_loss(scp).item() > base + 1.0
    none = dict(batch, source=torch.full_like(batch["source"], REL))
    assert module.value_loss(none).item() == 0.0
    # the training loss adds it to the policy's terms, equally weighted
    out = module._losses(batch)
    assert out["loss"].item() == pytest.approx((out["loss_action"] + out["loss_state"] + out["loss_value"]).item())


def test_value_only_training_leaves_the_policy_as_it_was() -> None:
    torch.manual_seed(0)
    module, batch = _module("optim.trainable=value", "optim.lr=1e-2", "optim.warmup_steps=0", "optim.schedule=constant")
    before = {k: v.clone() for k, v in module.model.state_dict().items()}
    out = module._losses(batch)
    assert set(out) == {"loss", "loss_value"}  # the transformer is not run
    opt = module.configure_optimizers()["optimizer"]
    for _ in range(3):
        loss = module._losses(batch)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = module.model.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith("value_head.") for k in changed)
    assert module._losses(batch)["loss"].item() < out["loss"].item()
    with pytest.raises(ValueError, match="needs a value output"):
        _module("optim.trainable=value", "model.value_width=0")


@pytest.mark.slow  # two tiny training runs (~20 s)
def test_value_head_added_to_published_weights(tmp_path: Path) -> None:
    """init_from a bundle without a value output + model.value_width: the policy's weights are the source's exactly
    (frozen), the value head is new, the exported bundle has one and prices states as its head does."""
    common = ("logger.kind=none", "model.layout=stacked", "trainer.checkpoint_every_n_steps=100")
    src = train(tiny_config(tmp_path / "src", "trainer.max_steps=3", *common), SourcedToyData(n=32))
    assert src.planner_dir is not None
    source = Planner.from_pretrained(src.planner_dir)
    assert not source.has_value
    value = ("model.value_width=16", "optim.trainable=value", "trainer.max_steps=4", f"init_from={src.planner_dir}")
    run = train(tiny_config(tmp_path / "value", *common, *value), SourcedToyData(n=32))
    assert run.planner_dir is not None
    planner = Planner.from_pretrained(run.planner_dir)
    assert planner.has_value
    assert planner.extra["value_added_to"] == str(src.planner_dir) and "finetuned_from" not in planner.extra
    assert planner.rtg_scale == source.rtg_scale
    want, got = source.model.state_dict(), planner.model.state_dict()
    assert all(torch.equal(got[k], want[k]) for k in want)
    assert {k for k in got if k not in want} == {k for k in got if k.startswith("value_head.")}
    sc = planner.scenario
    p = sc.sample(np.random.default_rng(0))
    X = np.stack([p.x0, p.goal])
    ctg = planner.cost_to_go([p, p], X, 3)
    st = planner.stats
    norm = lambda k, a: torch.as_tensor(st.normalize(k, a), dtype=torch.float32)[:, None]  # noqa: E731
    v = planner.model.value(norm("goals", np.stack([p.goal, p.goal])), norm("states", X), torch.full((2, 1), 3))
    assert ctg == pytest.approx(-st.denormalize("rtg", v.double().detach().numpy())[:, 0, 0], rel=1e-3)  # float32


def test_init_from_weights_must_fit_but_for_a_new_value_head() -> None:
    cfg = ModelConfig(state_dim=6, control_dim=3, n_embd=16, n_layer=1, n_head=2, max_steps=12, layout="stacked")
    plain = TrajectoryGPT(cfg)
    valued = TrajectoryGPT(ModelConfig(**{**cfg.__dict__, "value_width": 8}))
    load_source_weights(valued, plain.state_dict())  # a value head the source lacks: fine
    assert all(torch.equal(valued.state_dict()[k], v) for k, v in plain.state_dict().items())
    with pytest.raises(ConfigError, match="has a value output"):
        load_source_weights(TrajectoryGPT(cfg), valued.state_dict())
    partial = {k: v for k, v in plain.state_dict().items() if not k.startswith("action_head")}
    with pytest.raises(ConfigError, match="missing"):
        load_source_weights(TrajectoryGPT(cfg), partial)


def test_models_without_a_value_output_keep_the_ledger(toy, toy_stats: NormStats) -> None:
    """One rule wherever a mode is resolved (``rtg_feed``: evaluate, the metrics, DAgger, the demo, a provider):
    ``value`` declares the ledger as its fallback, so a model without a value output runs ``running`` and is named
    so; the zoo's cards run such a parent beside its value model under ``protocol=recommended``."""
    from ttompc.mpc.methods import METHODS
    from ttompc.mpc.rtg import RTG_MODES, ValueRTG
    from ttompc.mpc.settings import MPCSettings

    cfg = ModelConfig(state_dim=6, control_dim=3, n_embd=16, n_layer=1, n_head=2, max_steps=12, layout="stacked")
    planner = Planner(TrajectoryGPT(cfg), toy, toy_stats)
    assert not planner.has_value
    assert rtg_feed("value", planner).name == "running" and ValueRTG.fallback == "running"
    assert rtg_feed("oracle", planner).name == "oracle"
    assert TTOProvider(planner, rtg_mode="value").rtg_mode == "running"
    assert METHODS["R-FT-TTO-MPC"].label(MPCSettings(rtg_mode="value"), planner) == "R-FT-TTO-MPC"
    assert [m for m, c in RTG_MODES.items() if c.needs_value] == ["value"]
    with pytest.raises(ValueError, match="no value output"):
        planner.cost_to_go([toy.sample(np.random.default_rng(0))], np.zeros((1, 6)), 0)
    valued = Planner(TrajectoryGPT(ModelConfig(**{**cfg.__dict__, "value_width": 8})), toy, toy_stats)
    assert rtg_feed("value", valued).name == "value"
    assert METHODS["R-FT-TTO-MPC"].label(MPCSettings(rtg_mode="value"), valued) == "R-FT-TTO-MPC[rtg=value]"


def test_remaining_optimum_is_the_tail_of_the_optimum_on_its_own_path() -> None:
    """The oracle rtg's cost-to-go: along the optimum's own states the remaining optimum is its tail (no re-solve,
    cost-to-go falls by exactly each executed stage cost); off it, it re-plans from the measured state."""
    sc = get_scenario("quadrotor")
    p = sc.sample(np.random.default_rng(5))
    _, scp = solve_problem(sc, p)
    assert scp is not None and scp.success
    opt = RemainingOptimum((scp.X, scp.U))
    opt.reset(sc, p)
    X, U = opt(0, p.x0)
    assert np.array_equal(X[0], p.x0) and sc.cost(U) == pytest.approx(sc.cost(scp.U))
    X5, U5 = opt(5, scp.X[5])
    assert opt.replans == 0 and np.allclose(X5, scp.X[5:]) and len(U5) == p.n_steps - 5
    assert sc.cost(U5) == pytest.approx(sc.cost(scp.U) - sc.cost(scp.U[:5]))
    off = scp.X[6] + 0.05 * sc.state_units()
    X6, U6 = opt(6, off)
    assert opt.replans == 1 and np.array_equal(X6[0], off) and len(U6) == p.n_steps - 6
    assert np.max(np.abs(sc.rollout(p, U6, start=6, x=off)[-1] - p.goal)) < 1e-3
    with pytest.raises(ValueError, match="at step 6"):
        opt(2, p.x0)
    assert Window(6, p.n_steps - 6, p.n_steps).reaches_end


def test_dagger_refuses_value_targets_that_are_not_a_cost_to_go(toy, toy_stats: NormStats) -> None:
    """A model with a value output learns DAgger rows' rtg too: only plan rows with the expert's cost-to-go are a
    cost-to-go from the labelled step on; the paper's step labels carry the learner's ledger."""
    from ttompc.finetune.config import load_finetune_config
    from ttompc.finetune.loop import FinetuneError, check_value_labels

    recipe = Path(__file__).resolve().parents[1] / "recipes" / "freeflyer" / "finetune.yaml"
    cfg = ModelConfig(state_dim=6, control_dim=3, n_embd=16, n_layer=1, n_head=2, max_steps=12, value_width=8)
    valued = Planner(TrajectoryGPT(cfg), toy, toy_stats)
    plain = Planner(TrajectoryGPT(ModelConfig(**{**cfg.__dict__, "value_width": 0})), toy, toy_stats)
    ok = load_finetune_config(recipe, [])
    assert (ok.dagger.labels.kind, ok.dagger.labels.rtg) == ("plan", "expert")
    check_value_labels(ok, valued)
    for bad in (["dagger.labels.rtg=learner"], ["dagger.labels.kind=step"]):
        with pytest.raises(FinetuneError, match="value output"):
            check_value_labels(load_finetune_config(recipe, bad), valued)
        check_value_labels(load_finetune_config(recipe, bad), plain)  # no value output: any labels


def test_value_mode_feeds_the_models_cost_to_go_from_the_measured_state(toy, toy_stats: NormStats) -> None:
    """rtg_mode=value: the rtg fed at step t is −V(x_t, t) of the measured state, clipped to the training range;
    the ledger mode feeds nothing of its own (the context runs its running value)."""
    torch.manual_seed(0)
    cfg = ModelConfig(state_dim=6, control_dim=3, n_embd=16, n_layer=1, n_head=2, max_steps=12, value_width=8)
    planner = Planner(TrajectoryGPT(cfg), toy, toy_stats)
    p = toy.sample(np.random.default_rng(1))
    value, ledger = TTOProvider(planner, rtg_mode="value"), TTOProvider(planner)
    for prov in (value, ledger):
        prov.reset(toy, p, rel_cost=2.0)
    x = p.x0 + 0.3
    value.x = x
    lo, hi = value.rtg_range()
    want = float(np.clip(-planner.cost_to_go([p], x[None], 4)[0], lo, hi))
    assert value.conditioning(4) == pytest.approx(want)
    assert ledger.conditioning(4) is None
    with torch.no_grad():  # a value head that predicts a cost in range is fed as is
        planner.model.value_head[-1].bias.fill_(0.0)
        planner.model.value_head[-1].weight.zero_()
    mid = -float(planner.stats.denormalize("rtg", np.zeros(1))[0])  # V = the rtg mean's cost
    assert lo <= -mid <= hi and value.conditioning(4) == pytest.approx(-mid, rel=1e-5)


def test_a_batched_value_call_prices_each_state_as_a_lone_one(toy, toy_stats: NormStats) -> None:
    """``Planner.cost_to_go`` of B states in one call is each state's batch-1 value up to float rounding (1e-6
    relative); ``ValueRTG.prepare`` prices a group's members with it, and each member's feed reads its row once
    (a later call prices its state alone)."""
    from ttompc.mpc.rtg import ValueRTG
    from ttompc.mpc.tto import RolloutGroup

    torch.manual_seed(0)
    cfg = ModelConfig(state_dim=6, control_dim=3, n_embd=16, n_layer=1, n_head=2, max_steps=12, value_width=8)
    planner = Planner(TrajectoryGPT(cfg), toy, toy_stats)
    for layer in planner.model.value_head:  # torch's default initialisation: a cost-to-go that varies with the state
        if isinstance(layer, torch.nn.Linear):
            layer.reset_parameters()
    rng = np.random.default_rng(0)
    problems = [toy.sample(rng) for _ in range(10)]
    X = np.stack([p.x0 + rng.normal(scale=0.3, size=6) for p in problems])
    batched = planner.cost_to_go(problems, X, 4)
    lone = np.array([planner.cost_to_go([p], x[None], 4)[0] for p, x in zip(problems, X, strict=True)])
    np.testing.assert_allclose(batched, lone, rtol=1e-6, atol=0)
    assert np.ptp(lone) > 1e-3 * np.abs(lone).max()  # the states are priced apart
    group = RolloutGroup(planner)
    provs = [TTOProvider(planner, rtg_mode="value", group=group) for _ in problems]
    for prov, p, x in zip(provs, problems, X, strict=True):
        prov.reset(toy, p, rel_cost=2.0)
        prov.x = x
    ValueRTG.prepare(provs, 4)
    assert all(isinstance(prov.rtg, ValueRTG) and prov.rtg.priced is not None for prov in provs)
    fed = np.array([prov.rtg(prov, 4) for prov in provs])
    np.testing.assert_array_equal(fed, -batched)
    assert all(isinstance(prov.rtg, ValueRTG) and prov.rtg.priced is None for prov in provs)  # read once
    np.testing.assert_allclose([prov.rtg(prov, 4) for prov in provs], -lone, rtol=1e-6, atol=0)


@pytest.mark.parametrize(
    ("model", "parent"),
    [("freeflyer-ft-tto-v5", "freeflyer-ft-tto-v4"), ("quadrotor-ft-tto-v6", "quadrotor-ft-tto-v5")],
)
def test_shipped_value_models_plan_as_their_parents(model: str, parent: str) -> None:
    """The zoo's value models are their parents' policies with a value output added (their cards' claim): every
    policy weight equal, the parent's conditioning scale kept, and a value output the parent lacks."""
    new, old = Planner.from_pretrained(model), Planner.from_pretrained(parent)
    assert new.has_value and not old.has_value
    assert new.rtg_scale == old.rtg_scale and new.extra["value_added_to"] == parent
    want, got = old.model.state_dict(), new.model.state_dict()
    assert all(torch.equal(got[k], want[k]) for k in want)
    assert rtg_feed("value", new).name == "value" and rtg_feed("value", old).name == "running"


@pytest.mark.parametrize(("form", "activation"), [("gauss_newton", "silu"), ("gauss_newton", "gelu"), ("mlp", "relu")])
def test_the_value_models_expansion_is_the_heads_value_and_gradient(form: str, activation: str) -> None:
    """``ValueModel`` (numpy, the per-SCP-iteration expansion of a terminal cost) gives the torch head's cost-to-go
    J = −rtg at a state in the optimisation representation (through a linear map M to the model's), its gradient
    against central differences of the torch head, and a PSD Hessian: the Gauss–Newton σ·J_rᵀJ_r of that form,
    which is the Hessian of J where r is linear (checked against differences of the gradient with the head's
    pre-activations scaled into the activation's linear range), 0 for the piecewise-linear ReLU MLP."""
    from ttompc.policy.value import ValueModel

    torch.manual_seed(0)
    n = 6
    cfg = ModelConfig(n_embd=16, n_layer=1, n_head=2, max_steps=40, value_width=16, value_form=form,
                      value_activation=activation)  # fmt: skip
    model = TrajectoryGPT(cfg).double()
    stats = NormStats(
        mean={"states": np.full(n, 0.1), "actions": np.zeros(3), "goals": np.full(n, 0.2), "rtg": [-0.3], "ctg": [5.0]},
        std={"states": np.full(n, 2.0), "actions": np.full(3, 3e-3), "goals": np.ones(n), "rtg": [0.2], "ctg": [5.0]},
    )
    rng = np.random.default_rng(0)
    goal, x, M, t = rng.normal(size=n), rng.normal(size=n), rng.normal(size=(n, n)), 7

    def cost_to_go(x: np.ndarray) -> float:
        as_t = lambda a, key: torch.as_tensor(stats.normalize(key, a))[None, None]  # noqa: E731
        v = model.value(as_t(goal, "goals"), as_t(M @ x, "states"), torch.tensor([[t]]))
        return -float(stats.denormalize("rtg", v.detach().numpy()[0, 0])[0])

    e = ValueModel(model.value_head, cfg, stats).expand(goal, M @ x, t, M)
    assert e.value == pytest.approx(cost_to_go(x), rel=1e-12, abs=1e-12)
    fd = np.array([(cost_to_go(x + 1e-6 * d) - cost_to_go(x - 1e-6 * d)) / 2e-6 for d in np.eye(n)])
    np.testing.assert_allclose(e.gradient, fd, rtol=1e-6, atol=1e-8)
    assert np.linalg.eigvalsh(e.hessian).min() >= -1e-12
    if form == "mlp":
        assert not e.hessian.any()
        return
    with torch.no_grad():  # r nearly linear in the state: J = σ·½‖r‖² + const nearly quadratic
        model.value_head.net[0].weight.mul_(1e-3)
        model.value_head.net[4].weight.mul_(1e3)
    vm = ValueModel(model.value_head, cfg, stats)
    lin = vm.expand(goal, M @ x, t, M)
    hess_fd = np.stack([(vm.expand(goal, M @ (x + 1e-4 * d), t, M).gradient - lin.gradient) / 1e-4 for d in np.eye(n)])
    assert np.abs(hess_fd - lin.hessian).max() <= 1e-2 * np.abs(lin.hessian).max()


def test_the_value_loss_weighs_the_last_steps_as_set() -> None:
    """``optim.value_tail_steps``/``value_tail_weight``: an error on the last steps costs that much more."""
    torch.manual_seed(0)
    plain, batch = _module()
    tail, _ = _module("optim.value_tail_steps=3", "optim.value_tail_weight=5.0")
    tail.model.load_state_dict(plain.model.state_dict())
    late = batch["timesteps"] >= tail.model.cfg.max_steps - 3
    assert late.any() and (~late).any()
    moved = dict(batch, rtg=batch["rtg"] + 1.0 * late[..., None] * (batch["mask"] > 0)[..., None])
    ratio = (tail.value_loss(moved) - tail.value_loss(batch)) / (plain.value_loss(moved) - plain.value_loss(batch))
    assert ratio.item() > 1.5  # the late errors weigh 5x among the rows' weights


def test_a_new_value_form_trains_on_the_policy_of_its_source() -> None:
    """init_from a model whose value output has another form: the policy's weights load, the head starts fresh."""
    cfg = ModelConfig(state_dim=6, control_dim=3, n_embd=16, n_layer=1, n_head=2, max_steps=12, layout="stacked",
                      value_width=8)  # fmt: skip
    source = TrajectoryGPT(cfg)
    gn = TrajectoryGPT(ModelConfig(**{**cfg.__dict__, "value_form": "gauss_newton", "value_activation": "silu"}))
    load_source_weights(gn, source.state_dict())
    assert all(torch.equal(gn.state_dict()[k], v) for k, v in source.state_dict().items() if "value_head" not in k)


@pytest.mark.parametrize(
    ("form", "activation", "dtype"),
    [("mlp", "relu", torch.float32), ("gauss_newton", "silu", torch.float32), ("gauss_newton", "gelu", torch.float64)],
)
def test_cost_to_go_on_the_cpu_is_the_torch_heads(toy, toy_stats: NormStats, form: str, activation: str,
                                                  dtype: torch.dtype) -> None:  # fmt: skip
    """``Planner.cost_to_go`` on the CPU (the head in numpy, no torch call) gives the torch value output's
    cost-to-go up to the rounding of the model's dtype, for each form, and reads the current weights (an in-place
    update shows)."""
    torch.manual_seed(0)
    cfg = ModelConfig(state_dim=6, control_dim=3, n_embd=16, n_layer=1, n_head=2, max_steps=12, value_width=8,
                      value_form=form, value_activation=activation)  # fmt: skip
    planner = Planner(TrajectoryGPT(cfg).to(dtype), toy, toy_stats)
    for layer in planner.model.value_head.modules():  # torch's default initialisation: a value that varies
        if isinstance(layer, torch.nn.Linear):
            layer.reset_parameters()
    rng = np.random.default_rng(1)
    problems = [toy.sample(rng) for _ in range(5)]
    X = np.stack([p.x0 + rng.normal(scale=0.3, size=6) for p in problems])

    def torch_value(t: int) -> np.ndarray:
        st = planner.stats
        norm = lambda k, a: torch.as_tensor(st.normalize(k, a), dtype=dtype)[:, None]  # noqa: E731
        goals = np.stack([toy.model_goal(p) for p in problems])
        S = np.stack([toy.to_model_states(p, x[None], start=t)[0] for p, x in zip(problems, X, strict=True)])
        with torch.no_grad():
            v = planner.model.value(norm("goals", goals), norm("states", S), torch.full((len(X), 1), t))
        return -st.denormalize("rtg", v.double().numpy())[:, 0, 0]

    rtol = 1e-5 if dtype == torch.float32 else 1e-12
    for t in (0, 7):
        want = torch_value(t)
        assert np.ptp(want) > 1e-3 * np.abs(want).max()  # the states are priced apart
        np.testing.assert_allclose(planner.cost_to_go(problems, X, t), want, rtol=rtol, atol=rtol * np.abs(want).max())
    with torch.no_grad():
        next(planner.model.value_head.parameters()).mul_(1.5)
    np.testing.assert_allclose(planner.cost_to_go(problems, X, 7), torch_value(7), rtol=rtol,
                               atol=rtol * np.abs(torch_value(7)).max())  # fmt: skip
