"""The ``artdata`` command line.

Subcommands live in :mod:`articulated_dataset.commands`, one module each, exposing
``COMMANDS`` (a list of click commands); they are discovered automatically.

Errors: a :class:`~articulated_dataset.errors.UserError` (bad option, bad file, existing
output...) is printed as one line ``artdata: error: ...`` and exits with code 2; anything
else is a bug and keeps its traceback.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import sys

import click

from . import __version__
from .errors import UserError

EXIT_USER_ERROR = 2


class _Group(click.Group):
    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except UserError as exc:
            click.echo(f"artdata: error: {exc}", err=True)
            ctx.exit(EXIT_USER_ERROR)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="artdata")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
def main(verbose: int) -> None:
    """Articulated-object depth datasets: generate, inspect, load, score, baselines."""
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def _register_commands() -> None:
    from . import commands

    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{commands.__name__}.{info.name}")
        for cmd in getattr(module, "COMMANDS", []):
            main.add_command(cmd)


_register_commands()

if __name__ == "__main__":  # pragma: no cover
    main()
