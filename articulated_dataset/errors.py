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


#: How to install scipy, the optional dependency of ICP, the handle close-up and mixture scoring.
SCIPY_INSTALL = 'pip install scipy (or pip install -e ".[baselines]" from the repository checkout)'
#: How to install PyTorch's CPU build (a plain 'pip install torch' downloads GBs of CUDA libraries).
TORCH_INSTALL = ("pip install torch --index-url https://download.pytorch.org/whl/cpu (PyTorch's CPU build; "
                 "or bash scripts/setup.sh from the repository checkout)")


def import_optional(module: str, needed_by: str, install: str = SCIPY_INSTALL, *, user_error: bool = True):
    """``importlib.import_module(module)``; when its top-level package is not installed, one line
    naming what needs it and how to install it: a :class:`UserError` (the CLI prints it, exit 2),
    or with ``user_error=False`` a ModuleNotFoundError (Python APIs that promise that type).  A
    package that is installed but fails to import (something inside it is missing) stays a real
    error."""
    import importlib

    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = module.split(".")[0]
        if exc.name is None or exc.name.split(".")[0] != top:
            raise
        message = f"{needed_by} needs {top}, which is not installed: {install}"
        if user_error:
            raise UserError(message) from None
        raise ModuleNotFoundError(message, name=exc.name) from None
