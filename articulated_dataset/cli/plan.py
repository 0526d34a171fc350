"""``artdata plan``: grasp + waypoints that open one test object, optionally simulated."""

from __future__ import annotations

import math

import click

from articulated_dataset.cli.options import resolve_split_folder, split_folder
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.units import format_q

#: What ends the refusal to rebuild a third-party URDF object from recorded paths outside its
#: split folder (:func:`~articulated_dataset.generation.objects.stored_object_config`).
URDF_HINT = "; name the object's URDF with --urdf FILE (and --mesh-root DIR if it was generated with one)"


def object_file_options(what: str):
    """``--urdf FILE`` and ``--mesh-root DIR``: the files a third-party URDF object is rebuilt
    from (``what``: the rebuild, for the help), used only when their sha256 is the one the split
    recorded."""
    def decorate(f):
        f = click.option("--mesh-root", "mesh_root", type=click.Path(file_okay=False), default=None,
                         help="With --urdf: the folder its meshes are read from, as given to 'generate --mesh-root'  "
                              "[default: the URDF's folder].")(f)
        return click.option("--urdf", "urdf", type=click.Path(dir_okay=False), default=None,
                            help=f"A split generated with 'generate --urdf': the object's URDF, from which {what} "
                                 "rebuilds it (its recorded path is not opened outside the split folder); used only "
                                 "if it and its meshes are the files the split was generated from (sha256).")(f)
    return decorate


def check_object_file_options(urdf, mesh_root) -> None:
    """--mesh-root belongs to a --urdf."""
    if mesh_root is not None and urdf is None:
        raise UserError("--mesh-root is the folder of a --urdf's meshes: give --urdf FILE too")


def _fmt_vec(v, digits: int = 4) -> str:
    return "(" + ", ".join(f"{x:.{digits}f}" for x in v) + ")"


@click.command("plan")
@split_folder
@click.option("--index", type=int, required=True, help="Image index in the split (0-based, storage order).")
@click.option("--joint", type=int, default=0, show_default=True, help="Joint to actuate (label order).")
@click.option("--predictions", "predictions_path", type=click.Path(), default=None,
              help="Plan from this predictions.h5 (matched by sample_id) instead of the truth labels.")
@click.option("--model", "model", default=None,
              help="Estimate the kinematics from the image's stored depth with this model: a shipped model "
                   "(dense, dense-kinect2, mdn-small) or a checkpoint from 'artdata train'.")
@click.option("--closed-loop", is_flag=True,
              help="With --model and --simulate: look again while opening (extra views before grasping, one image "
                   "after each segment of the motion) and correct the plan; reports the images used.")
@click.option("--no-touch", is_flag=True,
              help="Closed loop without first closing the part by touch (configuration from the images only).")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of the sensor noise of the closed loop's rendered images (splits generated with --noise).")
@click.option("--threads", type=int, default=None, help="CPU threads for the model (default: torch's).")
@click.option("--target", default=None,
              help="Target configuration with units: 60deg, 1.0rad (revolute), 0.2m, 20cm (prismatic). "
                   "Default 60deg / 0.2m; clipped to the joint's range.")
@click.option("--step", default=None, help="Waypoint spacing with units (default 1deg / 1cm).")
@click.option("--simulate", is_flag=True, help="Execute the waypoints on the true object in MuJoCo and report the outcome.")
@click.option("--out", "out_path", type=click.Path(dir_okay=False), default=None, help="Write the plan (and outcome) as JSON.")
@object_file_options("plan")
@click.option("--quiet", "-q", is_flag=True, help="Do not list the waypoints.")
def plan_cmd(data_dir, data_option, index, joint, predictions_path, model, closed_loop, no_touch, seed, threads, target, step,
             simulate, out_path, urdf, mesh_root, quiet):
    """Plan end-effector waypoints that open joint JOINT of image INDEX's object in DIR (a
    generated split folder, <root>/<class>/<split>).

    The handle's grasp pose is estimated from the (true or predicted) axis pose, part offset
    and configuration; the waypoints carry it along the arc (revolute) or line (prismatic) to
    the target.  A split generated with --urdf is rebuilt from the URDF named with --urdf (its
    recorded path is opened only inside the split folder).  See docs/manipulation.md.
    """
    from articulated_dataset.manipulation.image_plan import plan_image, simulate_image_plan, write_plan_record

    data_dir = resolve_split_folder(data_dir, data_option)
    if index < 0:
        raise UserError(f"--index must be >= 0, got {index}")
    if model is not None and predictions_path is not None:
        raise UserError("give either --model (estimate from the image) or --predictions (a predictions file), not both")
    if closed_loop and (model is None or not simulate):
        raise UserError("--closed-loop needs --model (it re-estimates from new images) and --simulate (the scene it looks at)")
    if no_touch and not closed_loop:
        raise UserError("--no-touch applies to --closed-loop (the first grasp's touch)")
    if seed < 0:  # (numpy's SeedSequence raised a ValueError after the plan was printed: a traceback)
        raise UserError(f"--seed must be >= 0, got {seed}")
    if out_path == "-":  # other commands' '-' is standard output, where plan prints its summary
        raise UserError("--out -: plan writes its record to a file (its summary is printed); give a file name")
    if out_path:
        from articulated_dataset.core.safeio import check_can_create, check_outputs_distinct
        from articulated_dataset.methods.mdn.data import resolve_split_dir

        # the split read, the model and the predictions are never written over
        check_outputs_distinct([model, predictions_path], [out_path], input_folders=[resolve_split_dir(data_dir)])
        check_can_create(out_path)  # before any work: a read-only or missing place is one line now
    if model is not None and threads is not None and threads <= 0:
        raise UserError(f"--threads must be positive, got {threads}")
    check_object_file_options(urdf, mesh_root)

    def prepare_model():
        from articulated_dataset.cli.options import prepare_torch

        prepare_torch(threads)

    image = plan_image(data_dir, index, joint=joint, predictions_path=predictions_path, model=model,
                       closed_loop=closed_loop, simulate=simulate, target=target, step=step,
                       prepare_model=prepare_model, urdf=urdf, mesh_root=mesh_root, hint=URDF_HINT)
    obj, manifest, labels, plan, joint_type = image.obj, image.manifest, image.labels, image.plan, image.joint_type
    fq = lambda v: format_q(v, joint_type, 2)  # noqa: E731
    click.echo(f"{obj.class_name}/{manifest['split']} image {index} (object {int(labels['object_index'])}, "
               f"view {int(labels['image_index'])}, sample_id {image.sample_id}), joint {joint} ({joint_type}); "
               f"kinematics: {plan.source}")
    click.echo(f"axis: origin {_fmt_vec(plan.axis_origin)} m, direction {_fmt_vec(plan.axis_direction)}")
    click.echo(f"grasp: position {_fmt_vec(plan.grasp_pose[:3])} m, quaternion {_fmt_vec(plan.grasp_pose[3:])}")
    note = "" if image.clipped == image.q_target else f" (clipped from {fq(image.q_target)} to the joint range)"
    click.echo(f"q: {fq(plan.q_current)} -> {fq(plan.q_target)}{note}: {len(plan.waypoints)} waypoints, "
               f"step {fq(image.step)}")
    if not quiet:
        click.echo("    k      x_m      y_m      z_m       qw       qx       qy       qz")
        for k, wp in enumerate(plan.waypoints):
            click.echo(f"{k:5d} " + " ".join(f"{x:8.4f}" for x in wp))

    if simulate:
        result = simulate_image_plan(image, closed_loop=closed_loop, touch=not no_touch, seed=seed)
        if closed_loop:
            wrist = [v for v in result.views if v.get("wrist")]
            look = "" if not wrist else (f"; the handle close-up moved the grasp {100 * wrist[0]['grasp_moved_m']:.1f} cm"
                                         if wrist[0]["handle_found"] else "; no handle found in the close-up")
            click.echo(f"closed loop: {result.images_used} depth images used "
                       f"({sum(v['when'] == 'before grasp' for v in result.views)} before grasping, "
                       f"{sum(v['when'] == 'during motion' for v in result.views)} during the motion){look}"
                       + ("" if result.closed_stop is None else
                          "; closed stop felt" if result.closed_stop["found"] else "; closed stop not found"))
        limits = image.record["limits"]
        verdict = "SUCCESS" if result.success else f"FAILURE ({result.failure_reason()})"
        click.echo(f"simulation: true q {fq(result.q_start)} -> reached {fq(result.q_reached)} "
                   f"(target {fq(result.q_target)}, error {fq(result.error)}, tolerance {fq(limits['tolerance'])}); "
                   f"grasp {100 * result.grasp_error_m:.1f} cm from the handle; max force {result.max_force_n:.1f} N "
                   f"(limit {limits['max_force_n']:.0f}), max torque {result.max_torque_nm:.2f} N m "
                   f"(limit {limits['max_torque_nm']:.0f}), "
                   f"max tracking error {100 * result.max_position_error_m:.2f} cm / "
                   f"{math.degrees(result.max_rotation_error_rad):.2f} deg: {verdict}")
    if out_path:
        write_plan_record(out_path, image.record)
        click.echo(f"wrote {out_path}")


COMMANDS = [plan_cmd]
