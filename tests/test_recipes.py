"""Every training recipe loads against the schema, and describes the model it claims to."""

from __future__ import annotations

from pathlib import Path

import pytest

from ttompc.config import ConfigError
from ttompc.policy import TrajectoryGPT
from ttompc.training.config import load_train_config

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
TRAIN_RECIPES = sorted([*RECIPES.glob("*/pretrain.yaml"), *RECIPES.glob("*/tiny.yaml")])


def test_all_scenarios_have_recipes() -> None:
    names = {(p.parent.name, p.stem) for p in TRAIN_RECIPES}
    assert names >= {(s, r) for s in ("freeflyer", "quadrotor", "rpod") for r in ("pretrain", "tiny")}


@pytest.mark.parametrize("path", TRAIN_RECIPES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_recipe_loads_and_validates(path: Path) -> None:
    cfg = load_train_config(path)
    scenario = path.parent.name
    assert cfg.data.paths == [f"data/{scenario}-v1"]
    assert scenario in cfg.trainer.out_dir
    assert cfg.data.context_length <= cfg.model.max_steps
    n_params = TrajectoryGPT(cfg.model).num_parameters()
    if path.stem == "pretrain":
        assert (cfg.model.n_embd, cfg.model.n_layer, cfg.model.n_head) == (384, 6, 6)
        assert cfg.optim.accumulate == 8 and cfg.optim.grad_clip == 1.0
        assert 10.5e6 < n_params < 11.5e6
    else:
        assert n_params < 300_000


def test_unknown_key_and_wrong_type_name_the_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"optim\.learning_rate"):
        load_train_config(RECIPES / "freeflyer" / "tiny.yaml", ["optim.learning_rate=1e-3"])
    with pytest.raises(ConfigError, match=r"trainer\.max_steps"):
        load_train_config(RECIPES / "freeflyer" / "tiny.yaml", ["trainer.max_steps=many"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("model:\n  n_embd: 64\n  n_heads: 4\n")
    with pytest.raises(ConfigError, match="n_heads"):
        load_train_config(bad)
    with pytest.raises(ConfigError, match="divisible"):
        load_train_config(RECIPES / "freeflyer" / "tiny.yaml", ["model.n_head=5"])
