"""``UserError``: the one exception type for problems a user can fix (bad settings, missing files, unknown names).

``ttompc.cli.main`` prints a ``UserError`` as one line naming the problem (plus what to do) and exits with code 2,
without a traceback (``--debug`` or ``TTOMPC_DEBUG=1`` shows it). Library code raises subclasses of it (e.g.
``ConfigError``, the zoo's errors) so that callers in Python can still catch the specific type, with the words the
CLI prints.
"""

from __future__ import annotations


class UserError(Exception):
    """A problem in what the user asked for. ``hint`` says what to do about it (printed after the message)."""

    def __init__(self, message: str, hint: str | None = None) -> None:
        super().__init__(message)
        self.hint = hint

    def __str__(self) -> str:
        message = super().__str__()
        return f"{message}; {self.hint}" if self.hint else message


class ConfigError(UserError, ValueError):
    """A setting, recipe or override that does not match its schema (``ttompc.config``, ``ttompc.ranges``)."""


class InputError(UserError, ValueError):
    """An argument of a library call that cannot be used: another object than the call takes, another scenario's
    problem, a warm start of the wrong shape or with non-finite values."""
