"""Step 8 of the refinement: the network's outputs averaged with its outputs on the mirror image.

Where a class's mirror image is again an object of the class
(:attr:`~articulated_dataset.classes.base.ObjectClass.mirror_joints`: the cabinet hinged on either
side, the two-door cabinet, the drawer), the depth image reflected left-right is a second,
equally valid input.  The network is not exactly equivariant to the reflection (its errors on
the two images are partly independent), so averaging what it says about the two lowers the
error.  The network runs twice; the vote modes and steps 1-7 once, on the averaged outputs.
:func:`~.predict.fit_inference` uses the step only where it lowers a model's validation
position error by at least :data:`MIRROR_MIN_GAIN`.

* The mirror image of a depth image ``D`` with intrinsics ``K`` is ``D'[v, u] = D[v, W - 1 - u]``
  with ``c_x' = W - 1 - c_x`` (:func:`mirror_inputs`): every pixel back-projects to the original
  point reflected across the camera's ``x z`` plane (camera ``y`` negated).  Its network input
  is the original input reflected (:func:`mirror_network_input`), not computed again.
* The outputs on the mirror image are reflected back (:func:`merge_mirrored_outputs`): output
  pixel ``(v, w - 1 - u)`` of the mirror image is pixel ``(v, u)`` of the original (the output
  stride divides the image width), and its joint ``mirror_joints[j]`` is the original's joint ``j``.
  Averaged with the original's: the part logits (body; part ``j`` with the mirror's part
  ``mirror_joints[j]``), each joint's offset to its axis origin (its ``y`` negated: the origin and
  the pixel's point are both reflected), ``q`` (a door's opening angle and a drawer's travel are
  the same in the mirror image) and the vote confidences.  The axis frame, part offset and
  geometry are the original's (a frame's labelled orientation depends on the hinge side).

Averaging the network's outputs, rather than the two images' refined vote modes, runs the
refinement once instead of twice, at an equal or lower validation error.
"""

from __future__ import annotations

#: :func:`~.predict.fit_inference` averages with the mirror image only where that lowers the
#: validation position error by at least this fraction (the network runs twice).
MIRROR_MIN_GAIN = 0.03
#: The camera-frame axis a left-right reflection of the image negates (the camera's ``y`` points
#: left: :func:`~.features.backproject_torch`).
MIRROR_AXIS = 1


def with_mirror(refinement, mirror: bool):
    """A checkpoint's refinement (a :class:`~.refine.Refinement`, its dict or None) as a
    :class:`~.refine.Refinement`, without this step unless ``mirror`` (``predict --no-mirror``:
    one network pass instead of two, for a 4-6% higher position error)."""
    from dataclasses import replace

    from articulated_dataset.methods.dense.refine import as_refinement

    refinement = as_refinement(refinement)
    if mirror or refinement is None or refinement.mirror_joints is None:
        return refinement
    return replace(refinement, mirror_joints=None)


def mirror_intrinsics(K, width_px: int):
    """Intrinsics (B, 3, 3) (torch or numpy; a new array) that back-project the mirror images of
    ``width_px``-wide images to the reflected points: ``c_x' = W - 1 - c_x``."""
    K2 = K.clone() if hasattr(K, "clone") else K.copy()
    K2[:, 0, 2] = (width_px - 1) - K[:, 0, 2]
    return K2


def mirror_inputs(depth_m, K):
    """A batch of depth images (B, H, W) and intrinsics (B, 3, 3) (torch) -> their mirror images
    (reflected left-right) and the intrinsics that back-project them to the reflected points."""
    return depth_m.flip(-1), mirror_intrinsics(K, depth_m.shape[-1])


def mirror_network_input(x):
    """The network input (B, 9, H, W) of :func:`~.features.make_inputs` -> that of the mirror
    images (:func:`mirror_inputs`), to float rounding: reflected left-right, the relative points'
    and the normals' ``y`` negated (the anchor's ``y`` is negated with the points'), the pixel
    coordinate channels as they are (they do not depend on the image).  A new tensor."""
    from articulated_dataset.methods.dense.features import NORMAL_CHANNELS, PIXEL_CHANNELS, POINT_CHANNELS

    xm = x.flip(-1)
    xm[:, POINT_CHANNELS.start + MIRROR_AXIS].neg_()
    xm[:, NORMAL_CHANNELS.start + MIRROR_AXIS].neg_()
    xm[:, PIXEL_CHANNELS] = x[:, PIXEL_CHANNELS]
    return xm


def _merged_channels(n_joints: int, mirror_joints) -> tuple[list[int], list[int], list[float]]:
    """The output channels averaged with the mirror image's, the mirror image's channel each is
    averaged with, and the sign it takes (module docstring)."""
    from articulated_dataset.methods.dense.model import CONF_CHANNELS, JOINT_CHANNELS, OFFSET_CHANNELS, Q_CHANNEL

    perm = list(mirror_joints)
    own, other, sign = [0], [0], [1.0]  # the body's logit
    for j in range(n_joints):  # part j's logit
        own.append(1 + j)
        other.append(1 + perm[j])
        sign.append(1.0)
    first = 1 + n_joints
    for j in range(n_joints):
        a, b = first + j * JOINT_CHANNELS, first + perm[j] * JOINT_CHANNELS
        for c, s in [(c, -1.0 if c - OFFSET_CHANNELS.start == MIRROR_AXIS else 1.0)
                     for c in range(OFFSET_CHANNELS.start, OFFSET_CHANNELS.stop)] + \
                [(Q_CHANNEL, 1.0)] + [(c, 1.0) for c in range(CONF_CHANNELS.start, CONF_CHANNELS.stop)]:
            own.append(a + c)
            other.append(b + c)
            sign.append(s)
    return own, other, sign


def merge_mirrored_outputs(out, out_mirror, n_joints: int, mirror_joints):
    """Raw network outputs (B, C, h, w) of the images and of their mirror images -> the images'
    outputs with the channels of the module docstring averaged with the mirror images' (reflected
    back).  ``out`` is written in place and returned."""
    import torch

    own, other, sign = _merged_channels(n_joints, mirror_joints)
    own_t = torch.tensor(own)
    back = out_mirror.index_select(1, torch.tensor(other)).flip(-1)
    back.mul_(torch.tensor(sign, dtype=out.dtype).view(1, -1, 1, 1))
    out[:, own_t] = 0.5 * (out.index_select(1, own_t) + back)
    return out
