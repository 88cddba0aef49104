"""Configs as data: OmegaConf structured configs (dataclasses) loaded from YAML recipes plus dot-list overrides.

Unknown keys and wrong types are errors that name the offending key and file. Typed configs are converted to plain
containers (``to_container``) before they go into checkpoints, so nothing unpickles a config class.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

T = TypeVar("T")


class ConfigError(ValueError):
    """A recipe or override that does not match its schema."""


def load_config(schema: type[T], path: str | Path | None = None, overrides: Sequence[str] = ()) -> T:
    """Merge ``schema`` defaults <- YAML file <- ``key=value`` overrides and validate against the schema."""
    base = OmegaConf.structured(schema)
    layers: list[Any] = []
    where = "defaults"
    try:
        if path is not None:
            where = str(path)
            if not Path(path).is_file():
                raise ConfigError(f"config file not found: {path}")
            layers.append(OmegaConf.load(path))
        if overrides:
            where = f"overrides {list(overrides)}"
            bad = [o for o in overrides if "=" not in o]
            if bad:
                raise ConfigError(f"overrides must look like key=value, got {bad}")
            layers.append(OmegaConf.from_dotlist(list(overrides)))
        merged = OmegaConf.merge(base, *layers)
    except OmegaConfBaseException as err:
        raise ConfigError(f"invalid config ({where}): {err}") from None
    obj = OmegaConf.to_object(merged)
    return obj  # type: ignore[return-value]


def from_container(schema: type[T], data: dict[str, Any]) -> T:
    """Rebuild a typed config from a plain dict (e.g. stored in a checkpoint), validating it."""
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), OmegaConf.create(data))
    except OmegaConfBaseException as err:
        raise ConfigError(f"invalid stored config: {err}") from None
    return OmegaConf.to_object(merged)  # type: ignore[return-value]


def to_container(cfg: Any) -> dict[str, Any]:
    """Plain, primitive-only dict of a typed config (safe for ``save_hyperparameters`` and JSON)."""
    node = cfg if isinstance(cfg, DictConfig) else OmegaConf.structured(cfg)
    return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]
