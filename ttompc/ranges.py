"""What values each setting takes, declared on the schema, and the one checker of those declarations.

A settings dataclass declares a field's range with ``setting(default, ...)``: a ``dataclasses.field`` whose metadata
holds an ``Allowed`` (bounds, extra values such as -1 for "all", a list that may not be empty or repeat, a device
that must exist on this machine, a number of processes within this machine's cores). ``check_settings(cfg)`` walks
a config (a dataclass instance, or the OmegaConf node of one before it is built) and raises ``ConfigError`` at the
first value outside its range, in one line naming the dotted key, the value and what is allowed, e.g. ``invalid
data.batch_size=0: must be >= 1``. The command loader (``ttompc.config.load_command_config``) runs it on the merged
settings before anything is built, so the key is named in full; what a setting asks of the machine (a device,
processes) is checked by the command that runs on it (``check_devices``), so that a recipe for another machine still
loads and prints. ``Checked``, the base of the settings dataclasses, runs it on a dataclass's own fields when it is
built in Python (library calls refuse what the CLI refuses, in the same words, the key named from that dataclass).

Upper bounds, one rule each: an integer setting that declares no bound on a side lies within ``MAX_INT`` = 2**31 - 1
on that side (a count, size, seed or step beyond it is a typo: the largest datasets and runs of this project are
below 10**7, and torch and numpy count in 32-bit integers in places); a number of processes (``per_core``) is at most
that many per CPU core of the machine that runs it (more only share the same cores, each costing its memory and
start-up); a horizon is at most the scenario's N, checked by the command that knows the scenario.

Checks that relate several keys (split fractions that sum to 1, a horizon within the data's) stay in the
dataclasses' ``__post_init__`` or at the command that knows both sides.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from functools import cache
from typing import Any, Literal

from omegaconf import DictConfig, ListConfig, OmegaConf

from ttompc.errors import ConfigError

ALLOWED = "ttompc.allowed"  # the metadata key of a field's ``Allowed``
DeviceKind = Literal["torch", "lightning"]  # a torch device name, or a Lightning accelerator name
MAX_INT = 2**31 - 1  # the bound of an integer setting that declares none (module doc)
LIGHTNING_ACCELERATORS = ("auto", "cpu", "gpu", "cuda", "mps")


@dataclass(frozen=True)
class Allowed:
    """The values a setting takes: finite numbers within the bounds (``ge``/``gt``/``le``/``lt``) or among ``also``
    (e.g. -1 for "all"; ``meaning`` says what special values mean); an integer without a declared bound on a side
    within ``MAX_INT`` on that side; a list's items each so, the list non-empty (``nonempty``) and without repeats
    (``unique``); a device or accelerator that exists on this machine (``device``); a number of processes at most
    ``per_core`` per CPU core of this machine. None (an optional setting left to its default) is always allowed.
    What depends on the machine (``device``, ``per_core``) is checked only ``here`` (``check_devices``)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    also: tuple[Any, ...] = ()
    meaning: str = ""
    nonempty: bool = False
    unique: bool = False
    device: DeviceKind | None = None
    per_core: int | None = None

    @property
    def machine(self) -> bool:
        """Whether this setting asks something of the machine that runs it (a device, processes)."""
        return self.device is not None or self.per_core is not None

    def describe(self, here: bool = False, integer: bool = False) -> str:
        """What is allowed, in words: ``>= 1 or -1 (all)``, ``a non-empty list without repeats, each in [0, 1)``;
        ``here``: with this machine's part (its devices, its number of processes); ``integer``: with the bounds an
        integer has where none is declared (``MAX_INT``), for an integer beyond them."""
        if self.device is not None:
            return _device_text(self.device)
        if here and self.per_core is not None:
            return f"at most {self._most_processes()} on this machine ({self.per_core} per CPU core)"
        ge = self.ge if self.ge is not None or self.gt is not None or not integer else -MAX_INT
        le = self.le if self.le is not None or self.lt is not None or not integer else MAX_INT
        lo = f"[{_number(ge)}" if ge is not None else f"({_number(self.gt)}" if self.gt is not None else None
        hi = f"{_number(le)}]" if le is not None else f"{_number(self.lt)})" if self.lt is not None else None
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

    def admits(self, value: Any, here: bool = False) -> bool:
        """Whether ``value`` (a number, a string, a list of them, or None) is allowed; ``here``: also on this
        machine (its devices, its cores), else its declared bounds alone (where settings load)."""
        if value is None:
            return True
        if isinstance(value, (list, tuple)):
            if (self.nonempty and not value) or (self.unique and len(set(map(_shown, value))) < len(value)):
                return False
            return all(self._admits_one(v, here) for v in value)
        return self._admits_one(value, here)

    def _admits_one(self, value: Any, here: bool) -> bool:
        if value in self.also and type(value) is not bool:
            return True
        if self.device is not None:
            return not here or _device_exists(str(value), self.device)
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            return True  # types are OmegaConf's to check; a range applies to numbers
        if here and self.per_core is not None and value > self._most_processes():
            return False
        top = MAX_INT if isinstance(value, int) else math.inf  # an integer's bound when none is declared
        bounds: Sequence[tuple[float | None, Callable[[float, float], bool]]] = (
            (self.ge, lambda v, b: v >= b),
            (self.gt, lambda v, b: v > b),
            (self.le, lambda v, b: v <= b),
            (self.lt, lambda v, b: v < b),
            (None if self.le is not None or self.lt is not None else top, lambda v, b: v <= b),
            (None if self.ge is not None or self.gt is not None else -top, lambda v, b: v >= b),
        )
        return math.isfinite(value) and all(b is None or ok(value, b) for b, ok in bounds)

    def _most_processes(self) -> int:
        return int(self.per_core or 1) * (os.cpu_count() or 1)


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
    per_core: int | None = None,
) -> Any:
    """A dataclass field with a default (``default``, or ``factory`` for lists) and its declared range (``Allowed``)."""
    allowed = Allowed(ge, gt, le, lt, tuple(also), meaning, nonempty, unique, device, per_core)
    return field(default=default, default_factory=factory, metadata={ALLOWED: allowed})


def check_settings(cfg: Any, prefix: str = "", *, recurse: bool = True, devices: bool = False) -> None:
    """Raise ``ConfigError`` for the first field of ``cfg`` (a dataclass instance or a structured OmegaConf node)
    whose value its ``Allowed`` refuses, naming it ``<prefix><field>``; nested settings too when ``recurse``. What a
    setting asks of the machine is checked apart (``devices``: that alone, else the declared bounds), by the command
    that runs on it (``check_devices``): a recipe for a GPU machine still loads, and prints, on another."""
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
        if allowed is None or (devices and not allowed.machine):
            continue
        plain = OmegaConf.to_container(value) if isinstance(value, ListConfig) else value
        if not allowed.admits(plain, here=devices):
            items = plain if isinstance(plain, (list, tuple)) else [plain]
            integer = any(isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_INT for v in items)
            raise ConfigError(f"invalid {prefix}{f.name}={_shown(plain)}: must be {allowed.describe(devices, integer)}")


def check_devices(cfg: Any) -> None:
    """The device and accelerator settings of ``cfg`` (nested ones too) name what this machine has, and its numbers
    of processes are within its cores (``per_core``); raises ``ConfigError`` naming the key, the value and what this
    machine allows. Run by a command before it starts work."""
    check_settings(cfg, devices=True)


def check_device(value: Any, key: str = "device") -> None:
    """``value`` (a name or a ``torch.device``) is a torch device of this machine, else ``ConfigError`` in the words
    of ``check_devices`` for a setting ``key``: a library call taking a device refuses what the CLI refuses."""
    allowed = Allowed(device="torch")
    if not allowed.admits(str(value), here=True):
        raise ConfigError(f"invalid {key}={_shown(str(value))}: must be {allowed.describe()}")


@dataclass
class Checked:
    """Base of the settings dataclasses: building one checks its own fields' declared ranges (``check_settings``,
    keys named from this dataclass). A subclass with its own ``__post_init__`` calls ``super().__post_init__()``
    first."""

    def __post_init__(self) -> None:
        check_settings(self, recurse=False)


def _number(x: float) -> str:
    """A bound as written: whole numbers in full (``2147483647``), others as ``%g``."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e16 else f"{x:g}"


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
