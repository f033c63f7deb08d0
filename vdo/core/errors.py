"""The one exception type for user mistakes.

A `ConfigError` names the file, the field and what is expected. The command line prints it as one
line, ``error: FILE: FIELD: MESSAGE``, and exits with status 2; no traceback for user mistakes.
Checks that do not depend on each other run together (`Collect`) and raise every mistake they
found at once (`ConfigErrors`, one line each), so that a file with several is fixed in one go.
"""

from __future__ import annotations

from contextlib import contextmanager


class ConfigError(ValueError):
    """A user input (config file, mesh, command-line value) that vdo cannot use."""

    def __init__(self, file: str, field: str, message: str):
        self.file = str(file)
        self.field = field
        self.message = message
        super().__init__(f"{self.file}: {field}: {message}" if field else f"{self.file}: {message}")


class ConfigErrors(ConfigError):
    """Several `ConfigError`s found together (`Collect`): every up-front check ran, and each of
    its mistakes is one line of ``str()`` (and of the command line's output); `errors` holds
    them, the first also as this error's file, field and message."""

    def __init__(self, errors):
        self.errors = tuple(errors)
        first = self.errors[0]
        super().__init__(first.file, first.field, first.message)

    def __str__(self) -> str:
        return "\n".join(str(e) for e in self.errors)


class Collect:
    """Run several independent checks and report their mistakes together: each `check()` block
    that raises a `ConfigError` (or `ConfigErrors`) has it kept and the next block runs;
    `raise_all()` then raises the one error kept, or `ConfigErrors` of all of them."""

    def __init__(self):
        self.errors: list[ConfigError] = []

    @contextmanager
    def check(self):
        try:
            yield
        except ConfigError as exc:
            self.errors.extend(getattr(exc, "errors", (exc,)))

    def raise_all(self) -> None:
        if len(self.errors) == 1:
            raise self.errors[0]
        if self.errors:
            raise ConfigErrors(self.errors)


def check_time_limit(time_limit: float | None) -> None:
    """ConfigError for a command's `--time-limit` that is not a positive number of seconds (None:
    no limit)."""
    if time_limit is not None and not time_limit > 0:
        raise ConfigError("command line", "--time-limit",
                          f"must be a positive number of seconds (got {time_limit}); e.g. --time-limit 600")
