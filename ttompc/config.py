"""Configs as data: every command reads ``ttompc COMMAND [RECIPE.yaml] key=value ...`` through one loader.

``load_command_config(schema, recipe, overrides)`` merges, in order, the defaults of a typed OmegaConf structured
config (a dataclass), an optional YAML recipe (a mapping of keys) and dotted ``key=value`` overrides, checks every
value against the range its schema declares (``ttompc.ranges``), then builds the dataclass (so its ``__post_init__``
checks run). Every problem (YAML that does not parse, an unknown key, a wrong type, a value out of range, a missing
file, a failed check) raises ``ConfigError``, a ``UserError`` of one line that names the key and, for an unknown key,
the valid ones. Command-line flags are
only documented shortcuts: a command turns them into overrides (``shortcut_overrides``) before calling the loader.

Typed configs are converted to plain containers (``to_container``) before they go into checkpoints, so nothing
unpickles a config class.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException

from ttompc.errors import ConfigError
from ttompc.ranges import check_settings

T = TypeVar("T")
__all__ = ["ConfigError", "load_command_config"]


def load_command_config(schema_cls: type[T], recipe: str | Path | None = None, overrides: Sequence[str] = ()) -> T:
    """Schema defaults <- YAML ``recipe`` <- ``key=value`` ``overrides`` (dotted keys, e.g. ``data.paths=[a,b]``),
    validated against ``schema_cls`` (an OmegaConf structured dataclass); raises ``ConfigError``."""
    base = OmegaConf.structured(schema_cls)
    merged = base
    if recipe is not None:
        merged = _merge(base, merged, load_recipe(recipe), str(recipe))
    if overrides:
        bad = [o for o in overrides if "=" not in o]
        if bad:
            raise ConfigError(
                f"settings must look like key=value, got {' '.join(bad)}",
                "write e.g. seed=3 (a RECIPE.yaml may only come first)",
            )
        merged = _merge(base, merged, _parse_overrides(overrides), "the command line")
    try:
        check_settings(merged)
        return OmegaConf.to_object(merged)  # type: ignore[return-value]
    except MissingMandatoryValue as err:
        raise ConfigError(f"missing required setting {err.full_key!r}", f"pass {err.full_key}=VALUE") from None
    except OmegaConfBaseException as err:
        raise ConfigError(f"invalid setting {getattr(err, 'full_key', '')!r}: {_first_line(err)}") from None
    except ValueError as err:  # a schema's own __post_init__ check
        raise ConfigError(str(err)) from None


def load_recipe(recipe: str | Path) -> DictConfig:
    """The settings of the YAML file ``recipe``: a mapping of keys (an empty file is no settings); raises
    ``ConfigError`` in one line for a missing file, a folder, YAML that does not parse or a file of another shape."""
    path = Path(recipe)
    if path.is_dir():
        raise ConfigError(f"recipe {recipe} is a folder", "pass a YAML file (see recipes/)")
    if not path.is_file():
        raise ConfigError(f"recipe not found: {recipe}", "pass an existing YAML file (see recipes/)")
    try:
        layer = OmegaConf.load(path)
    except yaml.YAMLError as err:
        raise ConfigError(f"{recipe} is not valid YAML: {_yaml_problem(err)}") from None
    except (OmegaConfBaseException, UnicodeDecodeError, ValueError) as err:
        raise ConfigError(f"{recipe} is not a YAML file of settings: {_first_line(err)}") from None
    if not isinstance(layer, DictConfig):
        raise ConfigError(
            f"{recipe} holds a YAML {type(layer).__name__.removesuffix('Config').lower()}, not settings",
            "write one `key: value` per line (see recipes/)",
        )
    return layer


def _parse_overrides(overrides: Sequence[str]) -> DictConfig:
    """The ``key=value`` overrides as one layer; the first that does not parse is named in the ``ConfigError``."""
    for item in overrides:
        try:
            OmegaConf.from_dotlist([item])
        except yaml.YAMLError as err:
            raise ConfigError(
                f"cannot parse {item}: its value is not valid YAML ({_yaml_problem(err, where=False)})",
                "quote it or close its brackets, e.g. horizons=[10,30]",
            ) from None
        except (OmegaConfBaseException, ValueError) as err:
            raise ConfigError(f"cannot parse {item}: {_first_line(err)}") from None
    return OmegaConf.from_dotlist(list(overrides))


def _yaml_problem(err: yaml.YAMLError, where: bool = True) -> str:
    """A YAML error in one line: its problem and, with ``where``, its line and column (the parser's own text spans
    several lines)."""
    problem = getattr(err, "problem", None) or _first_line(err)
    mark = getattr(err, "problem_mark", None)
    if where and mark is not None:
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
    return str(problem)


def given_keys(recipe: str | Path | None = None, overrides: Sequence[str] = ()) -> set[str]:
    """The dotted keys a recipe and ``key=value`` overrides set explicitly (call it once ``load_command_config``
    accepted the same arguments): settings whose default follows the data may only fill in the others."""
    layers: list[Any] = [load_recipe(recipe)] if recipe is not None else []
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
        raise ConfigError(f"invalid stored config: {_first_line(err)}") from None
    check_settings(merged)
    return OmegaConf.to_object(merged)  # type: ignore[return-value]


def to_container(cfg: Any) -> dict[str, Any]:
    """Plain, primitive-only dict of a typed config (safe for ``save_hyperparameters`` and JSON)."""
    node = cfg if isinstance(cfg, DictConfig) else OmegaConf.structured(cfg)
    return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]
