"""Configs as data: every command reads ``ttompc COMMAND [RECIPE.yaml] key=value ...`` through one loader.

``load_command_config(schema, recipe, overrides)`` merges, in order, the defaults of a typed OmegaConf structured
config (a dataclass), an optional YAML recipe and dotted ``key=value`` overrides, then builds the dataclass (so its
``__post_init__`` checks run). Every problem (an unknown key, a wrong type, a missing file, a failed check) raises
``ConfigError``, a ``UserError`` that names the key and, for an unknown key, the valid ones. Command-line flags are
only documented shortcuts: a command turns them into overrides (``shortcut_overrides``) before calling the loader.

Typed configs are converted to plain containers (``to_container``) before they go into checkpoints, so nothing
unpickles a config class.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException

from ttompc.errors import UserError

T = TypeVar("T")


class ConfigError(UserError, ValueError):
    """A recipe or override that does not match its schema."""


def load_command_config(schema_cls: type[T], recipe: str | Path | None = None, overrides: Sequence[str] = ()) -> T:
    """Schema defaults <- YAML ``recipe`` <- ``key=value`` ``overrides`` (dotted keys, e.g. ``data.paths=[a,b]``),
    validated against ``schema_cls`` (an OmegaConf structured dataclass); raises ``ConfigError``."""
    base = OmegaConf.structured(schema_cls)
    merged = base
    if recipe is not None:
        path = Path(recipe)
        if not path.is_file():
            raise ConfigError(f"recipe not found: {recipe}", "pass an existing YAML file (see recipes/)")
        try:
            layer = OmegaConf.load(path)
        except Exception as err:  # YAML scanner/parser errors have no common base class here
            raise ConfigError(f"{recipe} is not valid YAML: {err}") from None
        merged = _merge(base, merged, layer, str(recipe))
    if overrides:
        bad = [o for o in overrides if "=" not in o]
        if bad:
            raise ConfigError(
                f"settings must look like key=value, got {' '.join(bad)}",
                "write e.g. seed=3 (a RECIPE.yaml may only come first)",
            )
        try:
            layer = OmegaConf.from_dotlist(list(overrides))
        except OmegaConfBaseException as err:
            raise ConfigError(f"cannot parse {' '.join(overrides)}: {_first_line(err)}") from None
        merged = _merge(base, merged, layer, "the command line")
    try:
        return OmegaConf.to_object(merged)  # type: ignore[return-value]
    except MissingMandatoryValue as err:
        raise ConfigError(f"missing required setting {err.full_key!r}", f"pass {err.full_key}=VALUE") from None
    except OmegaConfBaseException as err:
        raise ConfigError(f"invalid setting {getattr(err, 'full_key', '')!r}: {_first_line(err)}") from None
    except ValueError as err:  # a schema's own __post_init__ check
        raise ConfigError(str(err)) from None


def given_keys(recipe: str | Path | None = None, overrides: Sequence[str] = ()) -> set[str]:
    """The dotted keys a recipe and ``key=value`` overrides set explicitly (call it once ``load_command_config``
    accepted the same arguments): settings whose default follows the data may only fill in the others."""
    layers = [OmegaConf.load(recipe)] if recipe is not None else []
    if overrides:
        layers.append(OmegaConf.from_dotlist(list(overrides)))
    keys: set[str] = set()

    def walk(node: DictConfig, prefix: str) -> None:
        for key, value in node.items_ex(resolve=False):
            keys.add(f"{prefix}{key!s}")
            if isinstance(value, DictConfig):
                walk(value, f"{prefix}{key!s}.")

    for layer in layers:
        if isinstance(layer, DictConfig):
            walk(layer, "")
    return keys


def _merge(base: DictConfig, merged: DictConfig, layer: Any, where: str) -> DictConfig:
    try:
        return OmegaConf.merge(merged, layer)  # type: ignore[return-value]
    except ConfigKeyError as err:
        key = err.full_key or str(err.key)
        parent, _, _ = key.rpartition(".")
        node = OmegaConf.select(base, parent) if parent else base
        valid = ", ".join(str(k) for k in node.keys()) if isinstance(node, DictConfig) else "none"
        under = f" under '{parent}'" if parent else ""
        raise ConfigError(f"unknown setting '{key}' in {where}", f"valid keys{under}: {valid}") from None
    except OmegaConfBaseException as err:
        key = getattr(err, "full_key", None) or ""
        raise ConfigError(f"invalid value for '{key}' in {where}: {_first_line(err)}") from None


def _first_line(err: Exception) -> str:
    return str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__


def split_recipe(tokens: Sequence[str]) -> tuple[str | None, list[str]]:
    """``[RECIPE.yaml] key=value ...`` from a command's positional arguments: a first token without '=' is the
    recipe."""
    tokens = list(tokens)
    if tokens and "=" not in tokens[0]:
        return tokens[0], tokens[1:]
    return None, tokens


def add_config_arguments(parser: argparse.ArgumentParser, example: str) -> None:
    """The positional ``[RECIPE.yaml] [key=value ...]`` and ``--print-config`` every command takes."""
    parser.add_argument(
        "settings",
        nargs="*",
        metavar="[RECIPE.yaml] key=value",
        help=f"an optional YAML recipe, then dotted overrides, e.g. {example}",
    )
    parser.add_argument("--print-config", action="store_true", help="print the resolved config as JSON and exit")


def shortcut_overrides(args: argparse.Namespace, flags: Mapping[str, str] | Iterable[str]) -> list[str]:
    """``key=value`` overrides for the shortcut flags that were given (``flags``: argparse dest -> config key, or the
    dests of flags named like their config keys)."""
    pairs = flags.items() if isinstance(flags, Mapping) else ((name, name) for name in flags)
    return [f"{key}={getattr(args, dest)}" for dest, key in pairs if getattr(args, dest, None) is not None]


def command_config(schema_cls: type[T], args: argparse.Namespace, flags: Mapping[str, str] | Iterable[str] = ()) -> T:
    """The config of a command whose parser used ``add_config_arguments``: recipe, then shortcut flags, then the
    explicit ``key=value`` overrides (the last word wins)."""
    recipe, overrides = split_recipe(args.settings)
    return load_command_config(schema_cls, recipe, [*shortcut_overrides(args, flags), *overrides])


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
