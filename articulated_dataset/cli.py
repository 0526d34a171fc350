"""The ``artdata`` command line.

Subcommands live in :mod:`articulated_dataset.commands`, one module each, exposing
``COMMANDS`` (a list of click commands); they are discovered automatically.

Errors: a :class:`~articulated_dataset.errors.UserError` (bad option, bad file, existing
output...) is printed as one line ``artdata: error: ...`` and exits with code 2; anything
else is a bug and keeps its traceback.  A machine that cannot render offscreen (no EGL/OSMesa)
gets one line and exit code 3.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import sys

import click

from . import __version__
from .errors import RenderError, UserError

EXIT_USER_ERROR = 2
#: The machine lacks something rendering needs (EGL/OSMesa libraries).
EXIT_ENVIRONMENT_ERROR = 3


class _Group(click.Group):
    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except UserError as exc:
            click.echo(f"artdata: error: {exc}", err=True)
            ctx.exit(EXIT_USER_ERROR)
        except RenderError as exc:
            click.echo(f"artdata: error: {exc}", err=True)
            ctx.exit(EXIT_ENVIRONMENT_ERROR)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="artdata")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
def main(verbose: int) -> None:
    """Articulated-object depth datasets: generate, inspect, load, score, baselines."""
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def _check_mujoco_imports() -> None:
    """MuJoCo picks its GL backend when imported and raises if it cannot; say so in one line."""
    try:
        import mujoco  # noqa: F401
    except Exception as exc:  # ImportError, RuntimeError, OSError from the GL loaders
        backend = __import__("os").environ.get("MUJOCO_GL", "egl")
        click.echo(
            f"artdata: error: MuJoCo cannot start with MUJOCO_GL={backend!r} ({str(exc).splitlines()[0]}). "
            "Rendering needs EGL from Mesa (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri) "
            "or OSMesa (apt-get install libosmesa6, then MUJOCO_GL=osmesa).",
            err=True,
        )
        sys.exit(EXIT_ENVIRONMENT_ERROR)


def _register_commands() -> None:
    from . import commands

    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        for cmd in getattr(module, "COMMANDS", []):
            main.add_command(cmd)


_check_mujoco_imports()
_register_commands()

if __name__ == "__main__":  # pragma: no cover
    main()
