"""What values each setting takes, declared on the schema, and the one checker of those declarations.

A settings dataclass declares a field's range with ``setting(default, ...)``: a ``dataclasses.field`` whose metadata
holds an ``Allowed`` (bounds, extra values such as -1 for "all", a list that may not be empty or repeat, a device
that must exist on this machine). ``check_settings(cfg)`` walks a config (a dataclass instance, or the OmegaConf node
of one before it is built) and raises ``ConfigError`` at the first value outside its range, in one line naming the
dotted key, the value and what is allowed, e.g. ``invalid data.batch_size=0: must be >= 1``. The command loader
(``ttompc.config.load_command_config``) runs it on the merged settings before anything is built, so the key is
named in full; the devices a setting names are checked by the command that runs on them (``check_devices``), so
that a recipe for another machine still loads and prints. ``Checked``, the base of the settings dataclasses, runs it
on a dataclass's own fields when it is built in Python (library calls refuse what the CLI refuses, in the same words,
the key named from that dataclass).

Checks that relate several keys (split fractions that sum to 1, a horizon within the data's) stay in the
dataclasses' ``__post_init__`` or at the command that knows both sides.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from functools import cache
from typing import Any, Literal

from omegaconf import DictConfig, ListConfig, OmegaConf

from ttompc.errors import ConfigError

ALLOWED = "ttompc.allowed"  # the metadata key of a field's ``Allowed``
DeviceKind = Literal["torch", "lightning"]  # a torch device name, or a Lightning accelerator name
LIGHTNING_ACCELERATORS = ("auto", "cpu", "gpu", "cuda", "mps")


@dataclass(frozen=True)
class Allowed:
    """The values a setting takes: finite numbers within the bounds (``ge``/``gt``/``le``/``lt``) or among ``also``
    (e.g. -1 for "all"; ``meaning`` says what special values mean); a list's items each so, the list non-empty
    (``nonempty``) and without repeats (``unique``); a device or accelerator that exists on this machine
    (``device``). None (an optional setting left to its default) is always allowed."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    also: tuple[Any, ...] = ()
    meaning: str = ""
    nonempty: bool = False
    unique: bool = False
    device: DeviceKind | None = None

    def describe(self) -> str:
        """What is allowed, in words: ``>= 1 or -1 (all)``, ``a non-empty list without repeats, each in [0, 1)``."""
        if self.device is not None:
            return _device_text(self.device)
        lo = f"[{self.ge:g}" if self.ge is not None else f"({self.gt:g}" if self.gt is not None else None
        hi = f"{self.le:g}]" if self.le is not None else f"{self.lt:g})" if self.lt is not None else None
        if lo and hi:
            text = f"in {lo}, {hi}"
        elif lo or hi:
            op = {"[": ">=", "(": ">"}[lo[0]] if lo else {"]": "<=", ")": "<"}[hi[-1]]  # type: ignore[index]
            text = f"{op} {(lo or hi).strip('[]()')}"  # type: ignore[union-attr]
        else:
            text = "any value"
        if self.also:
            text += f" or {', '.join(json.dumps(v) for v in self.also)}"
        if self.meaning:
            text += f" ({self.meaning})"
        if self.nonempty or self.unique:
            listed = f"{'a non-empty list' if self.nonempty else 'a list'}{' without repeats' if self.unique else ''}"
            text = listed if text == "any value" else f"{listed}, each {text}"
        return text

    def admits(self, value: Any) -> bool:
        """Whether ``value`` (a number, a string, a list of them, or None) is allowed."""
        if value is None:
            return True
        if isinstance(value, (list, tuple)):
            if (self.nonempty and not value) or (self.unique and len(set(map(_shown, value))) < len(value)):
                return False
            return all(self._admits_one(v) for v in value)
        return self._admits_one(value)

    def _admits_one(self, value: Any) -> bool:
        if value in self.also and type(value) is not bool:
            return True
        if self.device is not None:
            return _device_exists(str(value), self.device)
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            return True  # types are OmegaConf's to check; a range applies to numbers
        bounds: Sequence[tuple[float | None, Callable[[float, float], bool]]] = (
            (self.ge, lambda v, b: v >= b),
            (self.gt, lambda v, b: v > b),
            (self.le, lambda v, b: v <= b),
            (self.lt, lambda v, b: v < b),
        )
        return math.isfinite(value) and all(b is None or ok(value, b) for b, ok in bounds)


def setting(
    default: Any = MISSING,
    *,
    factory: Callable[[], Any] | Any = MISSING,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    also: Sequence[Any] = (),
    meaning: str = "",
    nonempty: bool = False,
    unique: bool = False,
    device: DeviceKind | None = None,
) -> Any:
    """A dataclass field with a default (``default``, or ``factory`` for lists) and its declared range (``Allowed``)."""
    allowed = Allowed(ge, gt, le, lt, tuple(also), meaning, nonempty, unique, device)
    return field(default=default, default_factory=factory, metadata={ALLOWED: allowed})


def check_settings(cfg: Any, prefix: str = "", *, recurse: bool = True, devices: bool = False) -> None:
    """Raise ``ConfigError`` for the first field of ``cfg`` (a dataclass instance or a structured OmegaConf node)
    whose value its ``Allowed`` refuses, naming it ``<prefix><field>``; nested settings too when ``recurse``. The
    device settings are checked apart (``devices``: those alone, else all but those), by the command that runs on
    them (``check_devices``): a recipe for a GPU machine still loads, and prints, on another."""
    cls = OmegaConf.get_type(cfg) if isinstance(cfg, DictConfig) else type(cfg)
    if not (isinstance(cls, type) and is_dataclass(cls)):
        return
    for f in fields(cls):
        if isinstance(cfg, DictConfig) and (f.name not in cfg or OmegaConf.is_missing(cfg, f.name)):
            continue
        value = cfg[f.name] if isinstance(cfg, DictConfig) else getattr(cfg, f.name, None)
        nested = isinstance(value, DictConfig) or (is_dataclass(value) and not isinstance(value, type))
        if recurse and nested:
            check_settings(value, f"{prefix}{f.name}.", devices=devices)
            continue
        allowed = f.metadata.get(ALLOWED)
        if allowed is None or (allowed.device is not None) != devices:
            continue
        plain = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
        if not allowed.admits(plain):
            raise ConfigError(f"invalid {prefix}{f.name}={_shown(plain)}: must be {allowed.describe()}")


def check_devices(cfg: Any) -> None:
    """The device and accelerator settings of ``cfg`` (nested ones too) name what this machine has; raises
    ``ConfigError`` naming the key, the value and the devices here. Run by a command before it starts work."""
    check_settings(cfg, devices=True)


@dataclass
class Checked:
    """Base of the settings dataclasses: building one checks its own fields' declared ranges (``check_settings``,
    keys named from this dataclass). A subclass with its own ``__post_init__`` calls ``super().__post_init__()``
    first."""

    def __post_init__(self) -> None:
        check_settings(self, recurse=False)


def _shown(value: Any) -> str:
    try:
        return json.dumps(value)
    except (TypeError, ValueError):
        return repr(value)


@cache
def _devices() -> tuple[str, ...]:
    """The torch device types this machine runs (imports torch: only for a setting that names another than cpu)."""
    import torch

    found = ["cpu"]
    if torch.cuda.is_available():
        found += ["cuda", *(f"cuda:{i}" for i in range(torch.cuda.device_count()))]
    if getattr(torch.backends, "mps", None) is not None and torch.backends.mps.is_available():
        found.append("mps")
    return tuple(found)


def _device_exists(name: str, kind: DeviceKind) -> bool:
    if name == "cpu" or (kind == "lightning" and name == "auto"):
        return True
    if kind == "lightning":
        return name in LIGHTNING_ACCELERATORS and ("cuda" if name == "gpu" else name) in _devices()
    return name in _devices()


def _device_text(kind: DeviceKind) -> str:
    if kind == "lightning":
        here = ["auto", *(a for a in LIGHTNING_ACCELERATORS[1:] if _device_exists(a, kind))]
        return f"an accelerator of this machine: {', '.join(here)}"
    return f"a device of this machine: {', '.join(_devices())}"
