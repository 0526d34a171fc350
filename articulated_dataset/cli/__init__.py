"""The ``artdata`` command line: a thin face over the library.

Each subcommand lives in a module of this package (``cli/<module>.py``) exposing ``COMMANDS``
(a list of click commands) and does three things: parse its options, call the library
function that does the work, print what it returns.  :data:`COMMAND_MODULES` names the
module of each command, and a module is imported only when one of its commands runs or shows
its help (or ``artdata --help`` lists them all); ``options.py`` holds the option types and
set-up several commands share.  Importing this package loads no MuJoCo, OpenGL, torch or
jax: MuJoCo is imported only by the commands of :data:`MUJOCO_COMMANDS` when they run.

Errors: a :class:`~articulated_dataset.core.errors.UserError` (bad option, bad file, existing
output...) and every click usage error (unknown option, bad value, missing option or
argument, bad choice) are printed as one line ``artdata: error: ...`` and exit with code 2;
anything else is a bug and keeps its traceback.  A library message names the quantities it is
about (:func:`~articulated_dataset.core.errors.option`); the line shows each as the flag of the
command that ran (:func:`~articulated_dataset.cli.options.error_message`).  A machine that
cannot render offscreen (no EGL/OSMesa) gets one line and exit code 3 from the commands that
render; the others (``score``, ``info``, ``verify``, ...) work without a GL library.  A MuJoCo release outside the
supported range (:mod:`articulated_dataset.core.mujoco_support`) gets one line naming the range and exit
code 3 from the commands of :data:`MUJOCO_COMMANDS`.  A full disk (or standard
output on one) is also one line and exit code 3.
"""

from __future__ import annotations

import errno
import functools
import importlib
import logging
import os
import sys

import click

from articulated_dataset import __version__
from articulated_dataset.cli.options import error_message
from articulated_dataset.core.errors import RenderError, UserError
from articulated_dataset.core.mujoco_support import installed_mujoco_version, unsupported_mujoco

EXIT_USER_ERROR = 2
#: The machine lacks something a command needs (EGL/OSMesa libraries for rendering, disk space).
EXIT_ENVIRONMENT_ERROR = 3
#: Errors of writing that are the machine's (a full disk or quota, standard output on /dev/full):
#: one line and :data:`EXIT_ENVIRONMENT_ERROR`, not a traceback.
FULL_OUTPUT_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
#: Every subcommand and the module of this package that defines it
#: (tests/cli/test_import_light.py checks it against the modules' ``COMMANDS``).
COMMAND_MODULES = {
    "baseline": "baseline", "card": "card", "estimate": "estimate", "export": "export", "export-model": "export_model",
    "generate": "generate",
    "import-exr": "export", "info": "info", "ingest": "ingest", "models": "models", "plan": "plan",
    "predict": "predict", "score": "score", "show": "show", "train": "train", "verify": "verify",
}
#: Commands that always render with MuJoCo (the others render only on request and then
#: report a missing GL library through :class:`RenderError`, or never render).
RENDERING_COMMANDS = ("generate",)
#: Commands that may build MuJoCo models when they run (rendering, physics): MuJoCo is imported
#: before they start, without GL if its GL backend cannot start (see :func:`_import_mujoco`).
MUJOCO_COMMANDS = ("baseline", "generate", "plan", "show")
#: ``MUJOCO_GL`` value under which MuJoCo imports without any GL library (physics only).
_GL_DISABLED = "disable"

#: One-line message when MuJoCo cannot start with the chosen GL backend; None when it can.
MUJOCO_GL_PROBLEM: str | None = None


def _one_line(text: object) -> str:
    return " ".join(str(text).split())


def _usage_error_line(exc: click.UsageError, args=(), group: click.Group | None = None) -> str:
    """``artdata: error: <message> (see artdata CMD --help)`` for a click usage error.  Click gives
    some option errors no context (``--out`` without its value); their command is then read from
    the command line's ``args``: the words that name a command of ``group``, then of that command
    if it is a group, and so on."""
    words = ["artdata"]
    if exc.ctx is not None:
        words += exc.ctx.command_path.split()[1:]
    elif group is not None:
        command: click.Command = group
        for a in args or ():
            # (click's Group.get_command looks the name up without using the context)
            sub = command.get_command(None, a) if isinstance(command, click.Group) and isinstance(a, str) else None  # type: ignore[arg-type]
            if sub is not None:
                words.append(a)
                command = sub
    where = " ".join(words)
    return f"artdata: error: {_one_line(exc.format_message())} (see {where} --help)"


#: The key of ``ctx.meta`` (which a command shares with its subcommands) that holds the command that
#: runs (:class:`_Context`): a library error names the quantities it was given as that command's flags.
_RUNNING = "articulated_dataset.cli.running"


class _Context(click.Context):
    """A command's context that records its command as the one that runs (:data:`_RUNNING`); the
    innermost one, a subcommand's, is recorded last."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.meta[_RUNNING] = self.command


class _Group(click.Group):
    context_class = _Context

    def list_commands(self, ctx):
        return sorted(set(self.commands) | set(COMMAND_MODULES))

    def get_command(self, ctx, cmd_name):
        if cmd_name not in self.commands and cmd_name in COMMAND_MODULES:
            _load_commands(COMMAND_MODULES[cmd_name])
        return self.commands.get(cmd_name)

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        """Click's entry point with one-line errors: usage errors exit 2, other click
        exceptions (e.g. an interrupted run) exit with their own code, always on one line."""
        try:
            rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except click.exceptions.NoArgsIsHelpError as exc:
            if exc.ctx is not None and exc.ctx.parent is None:  # plain 'artdata': its help
                click.echo(exc.ctx.get_help())
                code = 0
            else:  # a group without its subcommand
                names = ", ".join(exc.ctx.command.list_commands(exc.ctx)) if exc.ctx is not None else ""  # type: ignore[attr-defined]  # a group
                click.echo(_usage_error_line(click.UsageError(f"missing command (one of: {names})", exc.ctx)), err=True)
                code = EXIT_USER_ERROR
        except click.UsageError as exc:
            click.echo(_usage_error_line(exc, sys.argv[1:] if args is None else args, self), err=True)
            code = EXIT_USER_ERROR
        except click.ClickException as exc:
            click.echo(f"artdata: error: {_one_line(exc.format_message())}", err=True)
            code = exc.exit_code
        except click.Abort:
            click.echo("artdata: error: aborted", err=True)
            code = 1
        else:
            code = rv if isinstance(rv, int) and not isinstance(rv, bool) else 0
        if not standalone_mode:
            return code
        sys.exit(code)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except UserError as exc:
            click.echo(f"artdata: error: {_one_line(error_message(exc, ctx.meta.get(_RUNNING)))}", err=True)
            ctx.exit(EXIT_USER_ERROR)
        except RenderError as exc:
            click.echo(f"artdata: error: {_one_line(exc)}", err=True)
            ctx.exit(EXIT_ENVIRONMENT_ERROR)
        except OSError as exc:
            if exc.errno not in FULL_OUTPUT_ERRNOS:
                raise
            # a full disk, or standard output redirected to one (> /dev/full): the machine's, not a bug
            click.echo(f"artdata: error: cannot write: {exc.strerror or exc}"
                       + (f" ({exc.filename})" if exc.filename else ""), err=True)
            ctx.exit(EXIT_ENVIRONMENT_ERROR)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="artdata")
@click.option("-v", "--verbose", count=True, help="More log output (-v info, -vv debug).")
def main(verbose: int) -> None:
    """Articulated-object depth datasets: generate, inspect, load, score, baselines."""
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def _mujoco_message(backend: str, exc: BaseException) -> str:
    first = (str(exc).splitlines() or [type(exc).__name__])[0]
    return (f"MuJoCo cannot start with MUJOCO_GL={backend!r} ({first}). "
            "Rendering needs EGL from Mesa (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri) "
            "or OSMesa (apt-get install libosmesa6, then MUJOCO_GL=osmesa).")


def _import_mujoco() -> None:
    """Import MuJoCo once.  If its GL backend cannot start, remember the one-line message
    (:data:`MUJOCO_GL_PROBLEM`) and import it without GL, so that commands which do not render
    still work; ``MUJOCO_GL`` is restored so that rendering later fails with the same cause."""
    global MUJOCO_GL_PROBLEM
    try:
        import mujoco  # noqa: F401
        return
    except Exception as exc:  # ImportError, RuntimeError, OSError, AttributeError from the GL loaders
        backend = os.environ.get("MUJOCO_GL", "egl")
        MUJOCO_GL_PROBLEM = _mujoco_message(backend, exc)
    for name in [m for m in sys.modules if m == "mujoco" or m.startswith("mujoco.")]:
        if not name.startswith("mujoco._"):  # compiled bindings cannot be imported twice
            del sys.modules[name]
    os.environ["MUJOCO_GL"] = _GL_DISABLED
    try:
        import mujoco  # noqa: F401,F811
    except Exception:  # MuJoCo itself is unusable: the commands that need it report it
        pass
    finally:
        os.environ["MUJOCO_GL"] = backend


def _prepared(cmd: click.Command) -> click.Command:
    """``cmd`` with MuJoCo imported before it runs (commands of :data:`MUJOCO_COMMANDS`), stopping
    with a one-line exit-3 message when that MuJoCo release is not supported, or when MuJoCo cannot
    render (commands of :data:`RENDERING_COMMANDS`); checked when it runs, so ``--help`` stays light.
    Each of its commands records itself as the one that runs (:class:`_Context`)."""
    for leaf in _leaves(cmd):
        leaf.context_class = _Context
    if cmd.name in MUJOCO_COMMANDS:
        for leaf in _leaves(cmd):
            leaf.callback = _with_mujoco(leaf.callback, cmd.name)
    for leaf in _leaves(cmd):
        for param in leaf.params:
            if isinstance(param.type, click.Path):
                param.callback = _refusing_empty_paths(param.callback)
    return cmd


def _refusing_empty_paths(callback):
    """A path option's callback that first refuses an empty path: ``--out ''`` named no folder,
    and ``generate`` wrote into the current one (``score --json ''`` wrote no report, exit 0)."""
    def checked(ctx, param, value):
        values = value if isinstance(value, (tuple, list)) else (value,)
        if any(isinstance(v, str) and not v.strip() for v in values):
            raise click.BadParameter("an empty path names no file or folder", ctx=ctx, param=param)
        return value if callback is None else callback(ctx, param, value)

    return checked


def _leaves(cmd: click.Command) -> list[click.Command]:
    if isinstance(cmd, click.Group):
        return [leaf for sub in cmd.commands.values() for leaf in _leaves(sub)]
    return [cmd]


def _with_mujoco(function, name: str):
    @functools.wraps(function)
    def checked(*args, **kwargs):
        _import_mujoco()
        unsupported = unsupported_mujoco(installed_mujoco_version())  # its scenes would not build
        if unsupported is not None:
            click.echo(f"artdata: error: {unsupported}", err=True)
            click.get_current_context().exit(EXIT_ENVIRONMENT_ERROR)
        if name in RENDERING_COMMANDS and MUJOCO_GL_PROBLEM is not None:
            click.echo(f"artdata: error: {MUJOCO_GL_PROBLEM}", err=True)
            click.get_current_context().exit(EXIT_ENVIRONMENT_ERROR)
        return function(*args, **kwargs)

    return checked


def _unavailable_command(name: str, exc: BaseException) -> click.Command:
    """Stand-in for a command whose module cannot be imported because MuJoCo is unusable."""
    message = MUJOCO_GL_PROBLEM or _mujoco_message(os.environ.get("MUJOCO_GL", "egl"), exc)

    @click.command(name, context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
                   add_help_option=False, help="Unavailable on this machine: MuJoCo cannot start.")
    def unavailable():
        click.echo(f"artdata: error: {message}", err=True)
        click.get_current_context().exit(EXIT_ENVIRONMENT_ERROR)

    return unavailable


def _load_commands(module_name: str) -> None:
    """Import ``articulated_dataset.cli.<module_name>`` and add its commands.  A module
    that imports MuJoCo at its top fails where MuJoCo's GL backend cannot start: then MuJoCo is
    imported without GL (:func:`_import_mujoco`) and the module again, and its commands stop
    with the one-line message when they render; if it still cannot be imported, they are
    stand-ins that say why."""
    name = f"{__name__}.{module_name}"
    try:
        module = importlib.import_module(name)
    except Exception as exc:
        if MUJOCO_GL_PROBLEM is not None or "mujoco" in sys.modules:
            raise
        _import_mujoco()
        if MUJOCO_GL_PROBLEM is None and "mujoco" in sys.modules:  # MuJoCo is fine: a bug
            raise
        try:
            module = importlib.import_module(name)
        except Exception:
            if "mujoco" in sys.modules:
                raise
            for cmd_name in [c for c, m in COMMAND_MODULES.items() if m == module_name]:
                main.add_command(_unavailable_command(cmd_name, exc))
            return
    for cmd in getattr(module, "COMMANDS", []):
        main.add_command(_prepared(cmd))
