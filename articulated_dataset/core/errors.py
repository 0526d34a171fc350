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
