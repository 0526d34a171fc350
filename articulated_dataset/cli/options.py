"""Option types and set-up that several commands share (no command of its own): the
``--class`` type, torch's preparation for the commands that run a network, and the flags that
library messages show (:func:`error_message`)."""

from __future__ import annotations

from collections.abc import Callable

import click

from articulated_dataset.core.errors import QuantityMessage, UserError, render_message

#: The flag of each quantity whose flag is not its name with dashes (``max_objects``:
#: ``--max-objects``), for a library message that names it (:func:`~articulated_dataset.core.errors.option`)
#: where the command that ran has no option of that name: a message about another command's option.
#: tests/cli/test_option_names.py checks it against every command's options.
FLAGS = {
    "as_json": "--json", "block_px": "--block", "camera_mount": "--camera", "camera_path": "--camera",
    "class_name": "--class", "csv_path": "--csv", "data_option": "--data", "fmt": "--format",
    "images_per_object": "--images", "intrinsics_path": "--intrinsics", "joint_names": "--joints",
    "json_path": "--json", "labels_path": "--labels", "like_path": "--like", "mask_path": "--mask",
    "mean_dir": "--mean-object", "mean_object": "--mean", "model_kind": "--model", "model_path": "--model",
    "n_objects": "--n", "n_samples": "--n", "out_path": "--out", "out_root": "--out",
    "per_sample_dir": "--per-sample", "predictions_path": "--predictions", "tables": "--table",
    "test_dir": "--test", "train_dir": "--train", "truth_path": "--truth", "urdf_class_name": "--class-name",
    "urdf_mesh_root": "--mesh-root", "urdf_path": "--urdf", "urdf_scale": "--scale",
}


def option_flag(param: click.Parameter) -> str | None:
    """The flag that names an option in messages: its first long flag (``--out`` of ``-o/--out``)."""
    if not isinstance(param, click.Option) or not param.opts:
        return None
    return next((o for o in param.opts if o.startswith("--")), param.opts[0])


def flag_of(command: click.Command | None) -> Callable[[str], str]:
    """The flag of each quantity a message names: the option of that name of ``command``, else
    :data:`FLAGS`, else the name with dashes."""
    own = {p.name: flag for p in (command.params if command is not None else ()) if (flag := option_flag(p))}
    return lambda name: own.get(name) or FLAGS.get(name) or "--" + name.replace("_", "-")


def error_message(exc: BaseException, command: click.Command | None = None) -> str:
    """``exc``'s message as the command line shows it: each quantity it names as a flag of
    ``command`` (by default the command that runs, :func:`flag_of`)."""
    if not isinstance(exc, QuantityMessage):
        return str(exc)
    if command is None:
        ctx = click.get_current_context(silent=True)
        command = ctx.command if ctx is not None else None
    return render_message(exc.message, flag_of(command))


class ClassChoice(click.ParamType):
    """Class names from the registry (validated lazily so --help lists them)."""

    name = "class"

    def get_metavar(self, param, ctx=None):
        """``[name|name|...]``: the registered class names, for --help."""
        from articulated_dataset.classes.registry import class_names

        return "[" + "|".join(class_names()) + "]"

    def convert(self, value, param, ctx):
        """The registered class's canonical name for ``value``; an unknown name fails the option with the registry's
        message."""
        from articulated_dataset.classes.registry import get_class

        try:
            return get_class(value).name
        except UserError as exc:
            self.fail(error_message(exc, ctx.command if ctx is not None else None), param, ctx)


#: ``--no-mirror`` of ``predict`` and ``estimate`` (the dense model's refinement without its mirror image:
#: :func:`articulated_dataset.methods.dense.mirror.with_mirror`).
no_mirror_option = click.option(
    "--no-mirror", is_flag=True,
    help="Dense model: skip the mirror image (the image reflected left-right, whose network outputs the cabinet "
         "and two-door cabinet models average with the image's): one network pass instead of two, 1.1-1.5x as "
         "fast for those classes, with a 4-6% higher position error.")

#: ``--precision`` of ``predict`` and ``estimate`` (the dense network's arithmetic:
#: :meth:`articulated_dataset.methods.dense.model.DenseNet.folded`).
precision_option = click.option(
    "--precision", type=click.Choice(["float32", "bfloat16"]), default="float32", show_default=True,
    help="Dense model: the network's arithmetic. bfloat16 runs it about twice as fast on CPUs with native bfloat16 "
         "(AVX512-BF16, AMX) and is emulated, slower, elsewhere; the predictions differ by its rounding "
         "(docs/dense.md, 'Precision').")


def prepare_torch(threads: int | None) -> int:
    """Import torch once for the command and set its threads, with the OpenMP wait policy
    :func:`~articulated_dataset.core.pool.configure_openmp_wait` chooses (threads that spin
    between operations where the machine has a free CPU for each, else passive waiting: spinning
    threads slow a busy 2-core machine ten-fold) unless the user set one, and the C allocator set
    to reuse freed memory (:func:`~articulated_dataset.core.pool.configure_allocator`)."""
    from articulated_dataset.core.errors import TORCH_INSTALL, import_optional
    from articulated_dataset.core.pool import configure_allocator, configure_openmp_wait

    configure_openmp_wait(threads if threads is not None and threads > 0 else None)
    configure_allocator()
    ctx = click.get_current_context(silent=True)
    import_optional("torch", f"artdata {ctx.info_name}" if ctx is not None else "this command", TORCH_INSTALL)
    from articulated_dataset.methods.mdn.train import configure_threads

    if threads is not None and threads <= 0:
        raise UserError(f"--threads must be positive, got {threads}")
    return configure_threads(threads)


#: The version from which the deprecated ``--data`` option is gone (it works until then, with a warning).
DATA_OPTION_REMOVED_IN = "0.3"


#: The ``--data DIR`` option that :func:`split_folder` and :func:`split_folders` keep until
#: :data:`DATA_OPTION_REMOVED_IN`.
_deprecated_data_option = click.option(
    "--data", "data_option", type=click.Path(), default=None, metavar="DIR",
    help=f"Deprecated (removed in {DATA_OPTION_REMOVED_IN}): give DIR as the argument.")


def split_folder(f):
    """The split folder a command reads, as its positional ``DIR`` argument (the one way every
    command names its main split; its docstring says what DIR is), with the older ``--data DIR``
    still accepted, with a warning, until :data:`DATA_OPTION_REMOVED_IN`.  The command receives
    ``data_dir`` and ``data_option`` and calls :func:`resolve_split_folder`."""
    f = _deprecated_data_option(f)
    return click.argument("data_dir", required=False, type=click.Path(), metavar="DIR")(f)


def resolve_split_folder(data_dir: str | None, data_option: str | None) -> str:
    """The split folder given as ``DIR`` or, deprecated, as ``--data DIR`` (a warning on standard
    error); both, or neither, is one line."""
    command = f"artdata {click.get_current_context().info_name}"
    if data_dir is not None and data_option is not None:
        raise UserError(f"the split folder is given twice ({data_dir} and --data {data_option}); give it once, as DIR")
    if data_option is not None:
        click.echo(f"artdata: warning: --data is deprecated and is removed in {DATA_OPTION_REMOVED_IN}; "
                   f"give the split folder as the argument: {command} {data_option} ...", err=True)
        return data_option
    if data_dir is None:
        raise UserError(f"missing the split folder DIR (see {command} --help)")
    return data_dir


def split_folders(f):
    """:func:`split_folder` for a command that reads one split folder or several (``DIR [DIR ...]``);
    the command receives ``data_dirs`` (a tuple) and ``data_option`` and calls
    :func:`resolve_split_folders`."""
    f = _deprecated_data_option(f)
    return click.argument("data_dirs", nargs=-1, type=click.Path(), metavar="DIR [DIR ...]")(f)


def resolve_split_folders(data_dirs: tuple[str, ...], data_option: str | None) -> list[str]:
    """The split folders given as ``DIR [DIR ...]`` or, deprecated, as one ``--data DIR``
    (:func:`resolve_split_folder`'s warning and errors)."""
    if len(data_dirs) > 1:
        if data_option is not None:
            raise UserError(f"the split folders are given twice ({' '.join(data_dirs)} and --data {data_option}); "
                            f"give them once, as DIR [DIR ...]")
        return list(data_dirs)
    return [resolve_split_folder(data_dirs[0] if data_dirs else None, data_option)]
