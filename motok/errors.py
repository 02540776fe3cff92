"""motok's exception hierarchy: which errors are the user's to fix and which are bugs.

Every error motok raises on purpose derives from :class:`MotokError`; the command line prints
those as one line and exits with code 2. Anything else that escapes a stage (a ``ValueError``
from numpy on a shape mismatch, a ``KeyError`` from a dict) is a bug in motok and keeps its
traceback, so it gets reported instead of looking like a mistake in the user's arguments.

Each stage keeps its own subclass (``ArtifactError``, ``ConfigError``, ``TokenizerError``, ...)
that also derives from the builtin it replaced, so ``except ValueError`` / ``except KeyError``
in library code and tests still catch it. This module imports nothing: any module can use it.
"""

from __future__ import annotations


class MotokError(Exception):
    """Base of every error motok raises deliberately, with a message meant for the user."""

    def __str__(self) -> str:
        # KeyError shows its argument as a repr (quotes and escapes); motok's messages are
        # sentences, so subclasses that are also KeyErrors print them as written.
        if len(self.args) == 1:
            return str(self.args[0])
        return super().__str__()


class UserError(MotokError, ValueError):
    """Bad input from the user: an argument, an option value, a name, the content of a file."""


class MissingFileError(UserError, FileNotFoundError):
    """A file or folder the user named does not exist."""


class UnknownNameError(UserError, KeyError):
    """A name the user gave (a clip, a split, a reference clip) is not where it was looked up."""
