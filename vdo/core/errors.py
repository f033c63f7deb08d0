"""The one exception type for user mistakes.

A `ConfigError` names the file, the field and what is expected. The command line prints it as one
line, ``error: FILE: FIELD: MESSAGE``, and exits with status 2; no traceback for user mistakes.
"""

from __future__ import annotations


class ConfigError(ValueError):
    """A user input (config file, mesh, command-line value) that vdo cannot use."""

    def __init__(self, file: str, field: str, message: str):
        self.file = str(file)
        self.field = field
        self.message = message
        super().__init__(f"{self.file}: {field}: {message}" if field else f"{self.file}: {message}")
