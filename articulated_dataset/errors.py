"""Exceptions that separate a user's mistake from a bug.

``UserError`` (and subclasses) mean "the input is wrong": the CLI prints its message on
one line and exits with code 2.  Anything else is a bug and propagates with a traceback.
"""

from __future__ import annotations


class UserError(Exception):
    """A problem with the user's input (bad option, bad file, existing output...)."""


class DataFormatError(UserError):
    """A file does not follow the articulated_dataset shard/prediction format."""


class RenderError(RuntimeError):
    """The offscreen renderer could not be created (missing EGL/OSMesa libraries)."""
