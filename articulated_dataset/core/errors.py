"""Exceptions that separate a user's mistake from a bug.

``UserError`` (and subclasses) mean "the input is wrong": the CLI prints its message on
one line and exits with code 2.  Anything else is a bug and propagates with a traceback.

Only the command line knows option names.  A message names a quantity that the user set with
:func:`option` (``f"{option('max_objects')} must be positive, got {n}"``): ``str()`` of the error
shows the bare name, as the library's callers spell it (``max_objects must be positive, got 0``),
and the command line shows the flag of the command that ran (``--max-objects must be positive,
got 0``) with :func:`render_message`.  :attr:`QuantityMessage.message` keeps the marks, for a
message that quotes another (``raise UserError(f"{path}: {exc.message}")``).
"""

from __future__ import annotations

import re
from collections.abc import Callable

#: Encloses a quantity's name in a message (:func:`option`): the ASCII unit separator, which no
#: message, path or value that a message quotes contains.
OPTION_MARK = "\x1f"
#: A quantity marked by :func:`option`; group 1 is its name.
_MARKED = re.compile(f"{OPTION_MARK}([A-Za-z_][A-Za-z0-9_]*){OPTION_MARK}")


def option(name: str) -> str:
    """The quantity ``name`` (a parameter name such as ``"max_objects"``) in an error message:
    ``str()`` of the error shows ``name``, the command line the flag that sets it."""
    if not name.isidentifier():
        raise ValueError(f"not a quantity name: {name!r}")
    return f"{OPTION_MARK}{name}{OPTION_MARK}"


def render_message(message: str, flag_of: Callable[[str], str]) -> str:
    """``message`` with each quantity marked by :func:`option` replaced by ``flag_of(name)``."""
    return _MARKED.sub(lambda m: flag_of(m.group(1)), message)


def _bare_name(name: str) -> str:
    return name


class QuantityMessage(Exception):
    """An exception whose message may name quantities marked by :func:`option`: ``str()`` shows
    their names, :attr:`message` keeps the marks (the command line shows each as its flag)."""

    def __str__(self) -> str:
        return render_message(super().__str__(), _bare_name)

    @property
    def message(self) -> str:
        """The message with its quantities still marked by :func:`option`."""
        return super().__str__()


class UserError(QuantityMessage):
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
