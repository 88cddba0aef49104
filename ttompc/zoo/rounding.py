"""Numbers rounded to what their standard error supports, as a card shows them (the model-index, ``ttompc zoo info``,
the table ``ttompc zoo metrics`` prints). The metrics file beside the bundle keeps full precision.

The rule: a standard error is shown with two significant digits and its mean to the same decimal place (0.8376 with
a standard error of 0.153 is 0.84 ± 0.15, 1049.3 ± 68.7 is 1049 ± 69, 446.9 ± 152 is 450 ± 150). A number without
a standard error (a share of counted runs, a step time, a mean whose standard error was not recorded) keeps three
significant digits, the precision of the evaluation reports' tables. A metric's standard error is the metric
``<key>_se`` of the same evaluation (``zoo/README.md``, metric keys).
"""

from __future__ import annotations

import math

SE_DIGITS = 2  # significant digits of a standard error
PLAIN_DIGITS = 3  # significant digits of a number without a standard error
SE_SUFFIX = "_se"


def _decimals(x: float, digits: int) -> int:
    """Decimal places that keep ``digits`` significant digits of ``x`` (negative: tens, hundreds, ...)."""
    return digits - 1 - math.floor(math.log10(abs(x))) if x else 0


def se_decimals(se: float) -> int:
    """Decimal places of a mean whose standard error is ``se`` (> 0): the place of the standard error's second
    significant digit."""
    return _decimals(float(f"{se:.{SE_DIGITS}g}"), SE_DIGITS)


def round_to_se(value: float, se: float | None) -> float:
    """``value`` rounded to the decimal place ``se`` supports (``se_decimals``); to three significant digits when
    ``se`` is None, not finite or not positive."""
    if se is None or not math.isfinite(se) or se <= 0:
        return float(round(value, _decimals(value, PLAIN_DIGITS)))
    return float(round(value, se_decimals(se)))


def format_with_se(value: float, se: float | None) -> str:
    """``value ± se`` at the precision ``se`` supports (``round_to_se``), e.g. ``0.84 ± 0.15``; ``value`` alone (at most
    three significant digits, trailing zeros dropped) without a usable ``se``. Never in exponent notation."""
    if se is None or not math.isfinite(se) or se <= 0:
        text = _fixed(value, _decimals(value, PLAIN_DIGITS))
        return text.rstrip("0").rstrip(".") if "." in text else text  # 0.9, not 0.900: no claim of precision
    places = se_decimals(se)
    return f"{_fixed(value, places)} ± {_fixed(se, places)}"


def _fixed(x: float, places: int) -> str:
    """``x`` rounded to ``places`` decimal places (negative: to tens, hundreds, ...), written without an exponent."""
    text = f"{round(x, places):.{max(places, 0)}f}"
    return text[1:] if text.startswith("-") and float(text) == 0 else text  # "-0.00" is 0


def shown(metrics: dict[str, int | float], key: str) -> str:
    """Metric ``key`` of one evaluation's ``metrics`` as a card shows it: with its standard error (``key_se``) when
    the evaluation has one, a count (an int) as it is, a standard error itself with two significant digits."""
    value = metrics[key]
    if isinstance(value, int):
        return str(value)
    if key.endswith(SE_SUFFIX):
        return _fixed(value, _decimals(value, SE_DIGITS))
    return format_with_se(value, metrics.get(key + SE_SUFFIX))


def rounded(metrics: dict[str, int | float], key: str) -> float:
    """Metric ``key`` rounded to its standard error (``key_se`` of ``metrics``): the value the model-index states."""
    return round_to_se(metrics[key], metrics.get(key + SE_SUFFIX))
