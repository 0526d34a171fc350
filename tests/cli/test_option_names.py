"""Only the command line knows option names.  A library message names the quantity it is about
(:func:`~articulated_dataset.core.errors.option`): ``str()`` of the error shows the quantity's
name, and ``artdata`` shows the flag of the command that ran in its place."""

from __future__ import annotations

import ast
import json
import pickle
import re
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner

import articulated_dataset
from articulated_dataset.cli import main
from articulated_dataset.cli.options import FLAGS, error_message, flag_of, option_flag
from articulated_dataset.core.errors import OPTION_MARK, UserError, option, render_message
from helpers_core import assert_one_line_error

#: A command-line flag in a message.
FLAG = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
#: The package's own folder; everything in it but ``cli/`` is the library.
PACKAGE = Path(articulated_dataset.__file__).parent
#: The exceptions whose messages the command line prints as ``artdata: error: ...``.
ERROR_CLASSES = ("UserError", "DataFormatError")


def _called_name(func: ast.expr) -> str | None:
    return func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else None


def flags_in_messages(source: str) -> list[tuple[int, str]]:
    """(line, flag) of each flag in a string constant of a ``raise`` statement or of a
    ``UserError(...)`` / ``DataFormatError(...)`` call of ``source``."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Raise) and node.exc is not None:
            root = node.exc
        elif isinstance(node, ast.Call) and _called_name(node.func) in ERROR_CLASSES:
            root = node
        else:
            continue
        for part in ast.walk(root):
            if isinstance(part, ast.Constant) and isinstance(part.value, str):
                found.update((part.lineno, flag) for flag in FLAG.findall(part.value))
    return sorted(found)


def library_files() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if p.relative_to(PACKAGE).parts[0] != "cli")


def quantities_named(source: str) -> set[str]:
    """The names given as literals to :func:`option` (under any name it is imported as)."""
    tree = ast.parse(source)
    aliases = {a.asname or a.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
               and node.module == "articulated_dataset.core.errors" for a in node.names if a.name == "option"}
    return {node.args[0].value for node in ast.walk(tree)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in aliases
            and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)}


def leaf_commands() -> list[click.Command]:
    """Every command ``artdata`` runs (a group's subcommands, not the group)."""
    ctx = click.Context(main)
    todo, leaves = [main.get_command(ctx, name) for name in main.list_commands(ctx)], []
    while todo:
        cmd = todo.pop()
        if isinstance(cmd, click.Group):
            todo.extend(cmd.commands.values())
        else:
            leaves.append(cmd)
    return leaves


# --------------------------------------------------------------------------------------
# (a) the library names quantities, never flags
# --------------------------------------------------------------------------------------

def test_library_error_messages_hold_no_flag():
    found = [f"{path.relative_to(PACKAGE.parent)}:{line}: {flag}"
             for path in library_files() for line, flag in flags_in_messages(path.read_text(encoding="utf-8"))]
    assert not found, "flags in library messages (name the quantity with core.errors.option):\n" + "\n".join(found)


def test_the_scan_finds_a_flag_in_a_message():
    source = ('def f(n):\n'
              '    if n <= 0:\n'
              '        raise UserError(f"--max-objects must be positive, got {n}")\n'
              '    return DataFormatError("use --overwrite"), "--width in a plain string"\n')
    assert flags_in_messages(source) == [(3, "--max-objects"), (4, "--overwrite")]


def test_every_command_shows_its_own_flag_for_each_option():
    """:data:`FLAGS` (the fallback for a message about another command's option) agrees with every
    command: an option's name is shown as that option's flag wherever it is named."""
    wrong = [f"artdata {cmd.name}: {p.name} -> {flag_of(None)(p.name)}, not {option_flag(p)}"
             for cmd in leaf_commands() for p in cmd.params
             if option_flag(p) is not None and flag_of(None)(p.name) != option_flag(p)]
    assert not wrong, "\n".join(wrong)


def test_each_quantity_of_the_library_is_one_flag_in_every_command():
    names = set().union(*(quantities_named(path.read_text(encoding="utf-8")) for path in library_files()))
    assert {"max_objects", "class_name", "urdf_path", "workers"} <= names  # the scan reads the option() calls
    commands = leaf_commands()
    shown = {name: {flag_of(cmd)(name) for cmd in commands} for name in sorted(names)}
    several = {name: flags for name, flags in shown.items() if len(flags) != 1}
    assert not several, several


# --------------------------------------------------------------------------------------
# (b) the command line shows the flags; the library names the quantities
# --------------------------------------------------------------------------------------

def _object_class_from_options(chosen_class, /, **urdf):
    from articulated_dataset.core.camera import CameraConfig
    from articulated_dataset.generation.request import UrdfOptions, object_class_from_options

    return lambda tmp: object_class_from_options(chosen_class, UrdfOptions(**urdf), CameraConfig())


def _object_count(n, mean):
    from articulated_dataset.generation.request import object_count

    return lambda tmp: object_count(n, mean)


def _executor(name, **kwargs):
    from articulated_dataset.core.pool import get_executor

    return lambda tmp: get_executor(name, **kwargs)


def _tables(class_name, names):
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.core.tables import table_from_options

    return lambda tmp: table_from_options(get_class(class_name), names)


def _train(kind, n_splits):
    from articulated_dataset.methods.train import TrainSettings, train_model

    def call(tmp):
        splits = tuple(tmp / f"s{i}" for i in range(n_splits))
        return train_model(kind, TrainSettings(class_name="drawer", data=splits, out=tmp / "n.pt"))

    return call


#: An isolated object's depth (m) on an empty background, and its camera (fx, fy, cx, cy in px).
OBJECT_DEPTH_M = 2.0
CAMERA = {"fx": 100.0, "fy": 100.0, "cx": 47.5, "cy": 26.5}


def _depth_image(tmp: Path) -> np.ndarray:
    depth = np.zeros((54, 96), np.float32)
    depth[15:40, 30:65] = OBJECT_DEPTH_M
    np.save(tmp / "d.npy", depth)
    (tmp / "camera.json").write_text(json.dumps(CAMERA))
    return depth


def _estimate(model):
    import articulated_dataset as ad

    K = np.array([[CAMERA["fx"], 0.0, CAMERA["cx"]], [0.0, CAMERA["fy"], CAMERA["cy"]], [0.0, 0.0, 1.0]])
    return lambda tmp: ad.estimate(_depth_image(tmp), K, "drawer", model=model)


#: Messages of the library as the command line prints them, in full (tests/generation/test_generate_refusals.py,
#: tests/classes/test_realistic_tables.py and tests/training/test_train_mixture.py check parts of them), and as
#: ``str()`` of the library's error: (arguments, the command's line, the library call, its message).
#: ``estimate`` names an option of ``train``, which it has not (the flag comes from :data:`FLAGS`).
MESSAGES = {
    "mean-with-n": (["generate", "--class", "drawer", "--n", "2", "--mean"],
                    "--mean renders exactly one object (the class's mean object); drop --n 2",
                    _object_count(2, True),
                    "mean renders exactly one object (the class's mean object); drop n_objects 2"),
    "address-without-ray": (["generate", "--class", "drawer", "--n", "1", "--address", "auto"],
                            "--address is for --executor ray",
                            _executor("local", address="auto"),
                            "address is for executor ray"),
    "workers-zero": (["generate", "--class", "drawer", "--n", "1", "--workers", "0"],
                     "--workers must be positive, got 0",
                     _executor("local", workers=0),
                     "workers must be positive, got 0"),
    "joints-without-urdf": (["generate", "--class", "drawer", "--n", "1", "--joints", "a,b"],
                            "--joints is for --urdf objects",
                            _object_class_from_options("drawer", joints="a,b"),
                            "joints is for urdf_path objects"),
    "class-name-without-urdf": (["generate", "--class", "drawer", "--n", "1", "--class-name", "x"],
                                "--class-name is for --urdf objects",
                                _object_class_from_options("drawer", class_name="x"),
                                "urdf_class_name is for urdf_path objects"),
    "class-and-urdf": (["generate", "--class", "drawer", "--urdf", "x.urdf", "--n", "1"],
                       "give either --class or --urdf, not both",
                       _object_class_from_options("drawer", path="x.urdf"),
                       "give either class_name or urdf_path, not both"),
    "two-table-names": (["generate", "--class", "drawer", "--n", "1", "--table", "realistic", "--table", "paper"],
                        "give one table name (--table realistic or --table paper), not both",
                        _tables("drawer", ["realistic", "paper"]),
                        "give one table name (table realistic or table paper), not both"),
    "mdn-on-two-splits": (["train", "--model", "mdn", "--class", "drawer", "s0", "s1", "--out", "n.pt"],
                          "--model mdn trains on one split; give one split folder (--model dense trains on several)",
                          _train("mdn", 2),
                          "model_kind mdn trains on one split; give one split folder (model_kind dense trains on "
                          "several)"),
    "estimate-with-an-mdn": (["estimate", "d.npy", "--camera", "camera.json", "--class", "drawer",
                              "--model", "mdn-small"],
                             "--model mdn-small: single-image estimates use a dense model (the shipped 'dense' or a "
                             "'artdata train --model dense' checkpoint); run MDN models with 'artdata predict'",
                             _estimate("mdn-small"),
                             "model mdn-small: single-image estimates use a dense model (the shipped 'dense' or a "
                             "'artdata train model_kind dense' checkpoint); run MDN models with 'artdata predict'"),
}


@pytest.mark.parametrize("case", list(MESSAGES))
def test_the_command_line_shows_flags_and_the_library_quantities(case, tmp_path, monkeypatch):
    args, line, call, message = MESSAGES[case]
    monkeypatch.chdir(tmp_path)
    _depth_image(tmp_path)
    result = CliRunner().invoke(main, [*args, *(["--out", str(tmp_path / "out")] if args[0] == "generate" else [])])
    assert assert_one_line_error(result) == f"artdata: error: {line}"
    with pytest.raises(UserError) as info:
        call(tmp_path)
    assert str(info.value) == message


# --------------------------------------------------------------------------------------
# (c) the marks and their rendering
# --------------------------------------------------------------------------------------

def _dashed(name: str) -> str:
    return "--" + name.replace("_", "-")


def test_render_message_replaces_each_mark_by_the_flag():
    message = f"{option('max_objects')} must be positive; give {option('width')}/{option('height')} or {option('n')} 3"
    assert render_message(message, _dashed) == "--max-objects must be positive; give --width/--height or --n 3"
    assert render_message(message, str.upper) == "MAX_OBJECTS must be positive; give WIDTH/HEIGHT or N 3"


def test_render_message_leaves_text_without_marks_alone():
    for text in ("", "plain --text", f"a lone {OPTION_MARK} mark", f"{OPTION_MARK}not a name{OPTION_MARK}"):
        assert render_message(text, _dashed) == text


def test_option_takes_a_name_only():
    with pytest.raises(ValueError, match="not a quantity name"):
        option("--max-objects")


def test_an_error_shows_names_and_keeps_its_marks():
    exc = UserError(f"{option('max_objects')} must be positive, got 0")
    assert str(exc) == "max_objects must be positive, got 0"
    assert exc.message == f"{option('max_objects')} must be positive, got 0"
    assert pickle.loads(pickle.dumps(exc)).message == exc.message  # from a worker process
    quoted = UserError(f"a.pt: {exc.message}")
    assert error_message(quoted, None) == "a.pt: --max-objects must be positive, got 0"


def test_a_command_shows_its_own_flag_before_the_table():
    @click.command()
    @click.option("-m", "--mean-dir", "mean_dir")
    @click.option("--class-label", "class_name")
    def cmd(mean_dir, class_name):
        """A command whose options are named as no other command's."""

    exc = UserError(f"{option('mean_dir')} and {option('class_name')}; {option('max_objects')} {option('model_kind')}")
    assert error_message(exc, cmd) == "--mean-dir and --class-label; --max-objects --model"
    assert error_message(exc, None) == "--mean-object and --class; --max-objects --model"
    assert FLAGS["mean_dir"] == "--mean-object"


def test_other_exceptions_are_their_text():
    assert error_message(ValueError(f"x {OPTION_MARK}"), None) == f"x {OPTION_MARK}"


def test_an_interrupted_training_names_the_resume_option():
    from articulated_dataset.methods.train import TrainingInterrupted

    exc = TrainingInterrupted(f"interrupted; continue with {option('resume')}")
    assert str(exc) == "interrupted; continue with resume"
    assert error_message(exc, None) == "interrupted; continue with --resume"
