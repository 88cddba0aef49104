"""The one config loader: schema defaults <- YAML recipe <- dotted key=value, with errors that name the key."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import pytest

from ttompc.config import ConfigError, load_command_config, split_recipe
from ttompc.errors import UserError


@dataclass
class Inner:
    rate: float = 0.5
    salt: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.rate <= 1:
            raise ValueError(f"inner.rate must be in [0, 1], got {self.rate}")


@dataclass
class Schema:
    name: str = "a"
    count: int = 3
    mode: Literal["soft", "hard"] = "soft"
    paths: list[str] = field(default_factory=list)
    inner: Inner = field(default_factory=Inner)


def test_layers_apply_in_order(tmp_path: Path) -> None:
    recipe = tmp_path / "r.yaml"
    recipe.write_text("count: 5\ninner:\n  salt: 2\n")
    cfg = load_command_config(Schema, recipe, ["count=7", "paths=[x,y]", "inner.rate=0.25"])
    assert cfg == Schema(count=7, paths=["x", "y"], inner=Inner(rate=0.25, salt=2))
    assert load_command_config(Schema, None, []) == Schema()


@pytest.mark.parametrize(
    ("overrides", "pattern"),
    [
        (["cuont=1"], r"unknown setting 'cuont' in the command line; valid keys: name, count, mode, paths, inner"),
        (["inner.sault=1"], r"unknown setting 'inner.sault'.*valid keys under 'inner': rate, salt"),
        (["count=many"], r"'count'.*could not be converted"),
        (["mode=medium"], r"'mode'"),
        (["inner.rate=2"], r"inner.rate must be in \[0, 1\]"),
        (["count"], r"settings must look like key=value, got count"),
    ],
)
def test_errors_name_the_key(overrides: list[str], pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern) as info:
        load_command_config(Schema, None, overrides)
    assert isinstance(info.value, UserError) and "\n" not in str(info.value)


def test_recipe_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="recipe not found"):
        load_command_config(Schema, tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("cuont: 1\n")
    with pytest.raises(ConfigError, match=f"unknown setting 'cuont' in {bad}"):
        load_command_config(Schema, bad)


def test_split_recipe() -> None:
    assert split_recipe(["r.yaml", "a=1"]) == ("r.yaml", ["a=1"])
    assert split_recipe(["a=1", "b=2"]) == (None, ["a=1", "b=2"])
    assert split_recipe([]) == (None, [])
