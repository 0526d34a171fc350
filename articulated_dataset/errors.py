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


def check_memory(need_bytes: float, what: str) -> None:
    """Raise a :class:`UserError` naming ``what`` if ``need_bytes`` exceeds the memory this
    process can still allocate (unknown availability: no check).  Call it before allocating
    anything whose size comes from the user (image sizes, block sizes, counts)."""
    from .safeio import available_memory_bytes, format_bytes

    available = available_memory_bytes()
    if available is not None and need_bytes > available:
        raise UserError(f"{what} needs about {format_bytes(need_bytes)} of memory; this machine has "
                        f"{format_bytes(available)} available")
