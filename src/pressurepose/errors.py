"""The one exception class for bad input: `UserError`.

Raised where input enters the program - command-line values, files users hand us - with a
message that names the file, the field and what was expected. The command line prints a
UserError as one line and exits with status 2; every other exception is a bug in this package
and keeps its traceback. It subclasses ValueError so code (and tests) that expect a
ValueError from a check keep working; the CLI catches UserError alone, never every ValueError.
"""

from __future__ import annotations


class UserError(ValueError):
    """Bad input (a file, a field, an argument); the message says what was expected."""


__all__ = ["UserError"]
