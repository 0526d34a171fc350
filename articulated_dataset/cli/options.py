"""Option types and set-up that several commands share (no command of its own): the
``--class`` type and torch's preparation for the commands that run a network."""

from __future__ import annotations

import os

import click

from ..errors import UserError


class ClassChoice(click.ParamType):
    """Class names from the registry (validated lazily so --help lists them)."""

    name = "class"

    def get_metavar(self, param, ctx=None):
        from ..registry import class_names

        return "[" + "|".join(class_names()) + "]"

    def convert(self, value, param, ctx):
        from ..registry import get_class

        try:
            return get_class(value).name
        except UserError as exc:
            self.fail(str(exc), param, ctx)


def prepare_torch(threads: int | None) -> int:
    """Import torch once for the command (with passive OpenMP waiting unless the user chose
    a policy: spinning threads slow a busy 2-core machine ten-fold) and set its threads."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        import torch  # noqa: F401
    except ImportError:
        raise UserError("PyTorch is not installed; install it with: pip install torch==2.13.0") from None
    from ..models.mdn.train import configure_threads

    if threads is not None and threads <= 0:
        raise UserError(f"--threads must be positive, got {threads}")
    return configure_threads(threads)
