"""The one ``ttompc evaluate`` command line that reproduces a report from the settings it records
(``report_command``): what the README's figures print in their footers, and the form of the ``command`` a zoo card
prints under each evaluation.

The line is ``ttompc evaluate KIND``, then the models as ``--model`` and ``--ft-model``, the protocol's keys
(``SHOWN``, in that order, each that is set: a None, e.g. ``rtg_scale``, is the model's own), the protocol's
overridden settings as ``mpc.KEY=VALUE``, then every other recorded setting that differs from the command's default,
nested ones as dotted keys, in the recorded order. Left out: ``INERT`` settings (where the report went, how many
processes ran it: they change no number), and the scenario when a model names it (the command takes the model's).
A recorded setting the command no longer has is kept, so the line shows what ran.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from ttompc.model_slots import MODEL_SLOTS, slot_flag

INERT = ("out", "workers")  # recorded settings that do not change a report's numbers
MODELS = tuple((slot_flag(slot), key) for slot, key in MODEL_SLOTS.items())  # (flag, config key)
SHOWN = {
    "warmstart": ("problems", "seed", "nonconvex_only", "rtg_scale", "oracle_detours"),
    "mpc": ("problems", "seed", "horizons", "plants", "robust_blend", "rtg_scale", "protocol"),
}


def report_command(kind: str, config: dict[str, Any], defaults: Any) -> str:
    """The ``ttompc evaluate KIND`` command line (``kind``: "mpc" or "warmstart") that reproduces a report whose
    ``config`` section is ``config`` (module doc); ``defaults``: the command's settings dataclass built with its
    defaults (``ClosedLoopConfig()``, ``WarmStartConfig()``), whose values the line leaves out."""
    if kind not in SHOWN:
        raise ValueError(f"kind must be one of {list(SHOWN)}, got {kind!r}")
    parts = ["ttompc evaluate", kind]
    parts += [f"{flag} {config[key]}" for flag, key in MODELS if config.get(key)]
    parts += [f"{key}={_value(config[key])}" for key in SHOWN[kind] if config.get(key) is not None]
    if kind == "mpc":
        parts += [f"mpc.{key}={_value(value)}" for key, value in (config.get("mpc") or {}).items()]
    default = _flat(asdict(defaults))
    done = {*INERT, *SHOWN[kind], "mpc", *(key for _, key in MODELS)}
    if any(config.get(key) for _, key in MODELS):
        done.add("scenario")
    parts += [
        f"{key}={_value(v)}"
        for key, v in _flat(config).items()
        if key.split(".")[0] not in done and (key not in default or default[key] != v)
    ]
    return " ".join(parts)


def _flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, v in d.items():
        if isinstance(v, dict) and v:
            out |= _flat(v, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = v
    return out


def _value(v: Any) -> str:
    if isinstance(v, list):
        return "[" + ",".join(_value(x) for x in v) + "]"
    return "null" if v is None else "{}" if v == {} else str(v)
