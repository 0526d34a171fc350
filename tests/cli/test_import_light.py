"""The command line loads light: importing ``articulated_dataset.cli``, the help of every
command but ``generate`` and the run of a command that neither renders nor learns load no
MuJoCo, OpenGL, torch or jax (so ``artdata score --help`` works where EGL is missing), and
the CLI's table of command modules is true."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pytest

from articulated_dataset import cli
from helpers_core import assert_one_line_error

HEAVY = ("mujoco", "OpenGL", "torch", "jax")


def heavy_modules_after_cli(*args: str) -> list[str]:
    """Which of :data:`HEAVY` a fresh interpreter holds after ``artdata ARGS`` (checked at exit,
    whatever the exit code)."""
    code = ("import atexit, sys\n"
            f"atexit.register(lambda: print('HEAVY=' + ','.join(m for m in {HEAVY!r} if m in sys.modules)))\n"
            "from articulated_dataset.cli import main\n"
            "main()\n")
    out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True)
    line = [s for s in out.stdout.splitlines() if s.startswith("HEAVY=")]
    assert line, out.stderr
    return [m for m in line[-1][len("HEAVY="):].split(",") if m]


def test_importing_the_cli_is_light():
    code = ("import sys\nimport articulated_dataset.cli\n"
            f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


@pytest.mark.parametrize("command", ["baseline", "card", "estimate", "export", "export-model", "import-exr", "info", "ingest",
                                     "models", "plan", "predict", "score", "show", "train", "verify"])
def test_help_of_every_command_but_generate_is_light(command):
    """Help loads the command's module only: even the commands that run a network or build
    MuJoCo models import them when they run (``train --help`` imported the generator's
    module, and MuJoCo, for its --class type before cli.options)."""
    assert heavy_modules_after_cli(command, "--help") == []


def test_the_check_sees_mujoco():
    """The checks above can fail: the generator's module imports MuJoCo at its top."""
    assert "mujoco" in heavy_modules_after_cli("generate", "--help")


def test_reading_a_split_is_light(tmp_path):
    from articulated_dataset.generation import GenerationConfig, generate_split

    split = generate_split(GenerationConfig("drawer", split="test", n_objects=1, images_per_object=2), tmp_path)
    assert heavy_modules_after_cli("info", str(split)) == []
    assert heavy_modules_after_cli("verify", str(split)) == []


def test_command_modules_name_every_command():
    """:data:`cli.COMMAND_MODULES` is what the modules of ``articulated_dataset.cli`` define."""
    defined = {}
    for info in [m for m in pkgutil.iter_modules(cli.__path__) if m.name != "__main__"]:  # __main__ runs the CLI
        module = importlib.import_module(f"{cli.__name__}.{info.name}")
        for cmd in getattr(module, "COMMANDS", []):
            defined[cmd.name] = info.name
    assert defined == cli.COMMAND_MODULES
    assert set(cli.MUJOCO_COMMANDS) <= set(defined) and set(cli.RENDERING_COMMANDS) <= set(cli.MUJOCO_COMMANDS)


def test_without_gl_a_mujoco_command_still_runs_without_rendering(tmp_path):
    """``plan`` builds MuJoCo models without rendering: where the GL backend cannot start,
    MuJoCo is imported without GL before it runs, so its help and its own checks still work."""
    import os

    env = {**os.environ, "MUJOCO_GL": "no-such-backend"}
    code = "from articulated_dataset.cli import main; main()"
    res = subprocess.run([sys.executable, "-c", code, "plan", str(tmp_path / "missing"), "--index", "0"],
                         env=env, capture_output=True, text=True)
    assert "MuJoCo" not in assert_one_line_error(res, code=cli.EXIT_USER_ERROR)
