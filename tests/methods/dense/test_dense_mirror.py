"""Refinement step 8 (methods/dense/mirror.py): the network's outputs averaged with its outputs on
the mirror image.

The classes' ``mirror_joints`` registrations are checked against rendered pixels and labels: the
mirrored object (pose and hinge side reflected, joints' openings paired) renders as the reflected
depth image, with its joint ``k``'s axis origin at the reflection of joint ``mirror_joints[k]``'s.
"""

from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from articulated_dataset.classes.base import JointSpec, ObjectClass  # noqa: E402
from articulated_dataset.classes.registry import REVOLUTE, all_classes, get_class  # noqa: E402
from articulated_dataset.core.camera import CameraConfig  # noqa: E402
from articulated_dataset.methods.dense.data import DenseData, quantise_depth  # noqa: E402
from articulated_dataset.methods.dense.features import backproject_torch, make_inputs  # noqa: E402
from articulated_dataset.methods.dense.mirror import (  # noqa: E402
    MIRROR_AXIS,
    merge_mirrored_outputs,
    mirror_inputs,
    mirror_network_input,
)
from articulated_dataset.methods.dense.model import DenseConfig, DenseNet  # noqa: E402
from articulated_dataset.methods.dense.predict import predict_arrays  # noqa: E402
from articulated_dataset.methods.dense.refine import Refinement  # noqa: E402
from helpers_core import compile_object, final_object, generated_split, render_at  # noqa: E402

MIRRORED = [c for c in all_classes() if c.mirror_joints is not None]
#: Depth agreement (m) of a pixel of the mirrored object's image and the reflected image.
DEPTH_TOL_M = 0.002
#: Pixels allowed to differ (rasterisation ties along silhouettes).
MAX_DIFFERING_FRACTION = 0.005


def test_the_built_in_registrations():
    assert {c.name: c.mirror_joints for c in MIRRORED} == {"cabinet": (0,), "cabinet2": (1, 0), "drawer": (0,)}
    for name in ("microwave", "toaster", "refrigerator"):  # their mirror images are not objects of the class
        assert get_class(name).mirror_joints is None


@pytest.mark.parametrize("perm", [(0, 0), (1,), (1, 2, 0)])
def test_mirror_joints_must_pair_the_joints(perm):
    joints = (JointSpec("a", REVOLUTE, "pa"), JointSpec("b", REVOLUTE, "pb"), JointSpec("c", REVOLUTE, "pc"))[:max(len(perm), 2)]
    with pytest.raises(ValueError, match="mirror_joints"):
        ObjectClass(name="x", template="x.urdf", table=get_class("cabinet").table, joints=joints, mirror_joints=perm)


@pytest.mark.parametrize("obj_class", MIRRORED, ids=lambda c: c.name)
def test_the_mirror_image_is_an_object_of_the_class_with_its_joints_paired(obj_class):
    config, sample = final_object(obj_class.name, index=1)
    perm = list(obj_class.mirror_joints)
    mirrored = replace(sample, pose={**sample.pose, "y_m": -sample.pose["y_m"], "yaw_rad": -sample.pose["yaw_rad"]},
                       chirality=1 - sample.chirality if obj_class.sided else sample.chirality, q=sample.q[:, perm])
    K = config.camera.K
    W = config.camera.width_px
    assert K[0, 2] == pytest.approx((W - 1) / 2)  # the paper's camera: the reflection maps pixel centres onto each other
    _, model, data, info, labels = compile_object(config, sample)
    _, model2, data2, info2, labels2 = compile_object(config, mirrored)
    depth, _ = render_at(config, model, data, info, sample.q[0])
    depth2, _ = render_at(config, model2, data2, info2, mirrored.q[0])
    assert (depth > 0).mean() > 0.05
    differ = np.abs(depth2 - depth[:, ::-1]) > DEPTH_TOL_M
    assert differ.mean() < MAX_DIFFERING_FRACTION
    reflect = np.diag([1.0, 1.0, 1.0])
    reflect[MIRROR_AXIS, MIRROR_AXIS] = -1.0
    for k in range(obj_class.n_joints):
        assert np.allclose(labels2["axis_origin"][k], reflect @ labels["axis_origin"][perm[k]], atol=1e-6)
    # and the unpaired reading is wrong for the two-door cabinet (the test can fail)
    if perm != list(range(obj_class.n_joints)):
        assert not np.allclose(labels2["axis_origin"][0], reflect @ labels["axis_origin"][0], atol=1e-3)


def test_mirror_inputs_back_project_to_the_reflected_points():
    rng = np.random.default_rng(0)
    depth = torch.from_numpy(rng.uniform(1.0, 2.0, (2, 6, 9)).astype(np.float32))
    K = torch.tensor([[[50.0, 0, 3.7], [0, 50.0, 2.5], [0, 0, 1]], [[40.0, 0, 4.0], [0, 45.0, 3.0], [0, 0, 1]]])
    d2, K2 = mirror_inputs(depth, K)
    p = backproject_torch(depth, K)
    p2 = backproject_torch(d2, K2)
    expected = p.flip(-1).clone()
    expected[:, MIRROR_AXIS] *= -1
    assert torch.allclose(p2, expected, atol=1e-5)
    assert torch.equal(K, torch.tensor([[[50.0, 0, 3.7], [0, 50.0, 2.5], [0, 0, 1]], [[40.0, 0, 4.0], [0, 45.0, 3.0], [0, 0, 1]]]))


def _box_depths(n, H, W):
    depth = np.zeros((n, H, W), np.float32)
    for i in range(n):  # a slanted box face, off centre (so its mirror image differs)
        depth[i, H // 4 : 3 * H // 4, W // 5 + 10 * i : 4 * W // 5] = 1.4 + 0.002 * np.arange(W // 5 + 10 * i, 4 * W // 5)
    return depth


def test_the_mirror_network_input_is_the_input_of_the_mirror_image():
    """Reflecting the input equals computing it from the reflected depth and intrinsics."""
    cam = CameraConfig()
    depth = torch.from_numpy(_box_depths(3, cam.height_px, cam.width_px))
    K = torch.from_numpy(np.repeat(cam.K[None].astype(np.float32), 3, 0))
    K[1, 0, 2] += 7.3  # an off-centre principal point too
    x = make_inputs(depth, K)["x"]
    expected = make_inputs(*mirror_inputs(depth, K))["x"]
    got = mirror_network_input(x)
    assert torch.allclose(got, expected, atol=1e-5)
    assert not torch.allclose(x.flip(-1), expected, atol=1e-3)  # the y channels' signs matter


def _mirror_of(out, n_joints, perm):
    """The outputs a mirror-equivariant network would give on the mirror image (the inverse of the
    reflection merge_mirrored_outputs applies)."""
    m = out.flip(-1).clone()
    first = 1 + n_joints
    C = (out.shape[1] - first - 5) // n_joints
    for j in range(n_joints):  # the mirror's part perm[j] is the original's part j
        m[:, 1 + perm[j]] = out.flip(-1)[:, 1 + j]
        m[:, first + perm[j] * C : first + (perm[j] + 1) * C] = out.flip(-1)[:, first + j * C : first + (j + 1) * C]
        m[:, first + perm[j] * C + MIRROR_AXIS] *= -1  # offset's y
    return m


@pytest.mark.parametrize("perm", [(0,), (1, 0)])
def test_merging_the_outputs_of_an_equivariant_network_changes_nothing(perm):
    J = len(perm)
    rng = np.random.default_rng(1)
    n_out = 1 + J + 16 * J + 5
    out = torch.from_numpy(rng.normal(size=(2, n_out, 3, 4)).astype(np.float32))
    mirror = _mirror_of(out, J, perm)
    assert torch.allclose(merge_mirrored_outputs(out.clone(), mirror, J, perm), out, atol=1e-6)
    if J == 2:  # read without the pairing, the joints are mixed up (the test can fail)
        assert not torch.allclose(merge_mirrored_outputs(out.clone(), mirror, J, (0, 1)), out, atol=1e-3)


def test_merge_averages_the_listed_channels_only():
    """Hand-worked: one joint, one row of two output pixels."""
    J = 1
    n_out = 1 + J + 16 * J + 5
    out = torch.zeros(1, n_out, 1, 2)
    mirror = torch.zeros(1, n_out, 1, 2)
    mirror[0, 1, 0, 1] = 4.0  # part logit at the mirror's right pixel = the original's left pixel
    mirror[0, 2 + 1, 0, 1] = 0.2  # offset y
    mirror[0, 2 + 0, 0, 0] = 0.6  # offset x at the right pixel
    mirror[0, 2 + 9, 0, 1] = 1.0  # q
    mirror[0, 2 + 3, 0, 1] = 5.0  # rot6: not averaged
    mirror[0, 2 + 13, 0, 1] = 2.0  # a vote confidence
    mirror[0, -1, 0, 1] = 3.0  # geometry: not averaged
    got = merge_mirrored_outputs(out, mirror, J, (0,))
    assert got[0, 1, 0, 0] == 2.0 and got[0, 1, 0, 1] == 0.0
    assert got[0, 2 + 1, 0, 0] == pytest.approx(-0.1)
    assert got[0, 2 + 0, 0, 1] == pytest.approx(0.3)
    assert got[0, 2 + 9, 0, 0] == 0.5 and got[0, 2 + 13, 0, 0] == 1.0
    assert got[0, 2 + 3].abs().sum() == 0 and got[0, -1].abs().sum() == 0
    assert got is out


def test_refinement_round_trips_step_8_and_older_checkpoints_read_without_it():
    ref = Refinement(frame=True, mirror_joints=(1, 0))
    d = ref.to_dict()
    assert d["mirror_joints"] == [1, 0]
    assert Refinement.from_dict(d) == ref
    old = {k: v for k, v in d.items() if k != "mirror_joints"}
    old["version"] = 4
    assert Refinement.from_dict(old).mirror_joints is None


class _Averaged(DenseNet):
    """A network whose outputs are another's averaged with its outputs on the mirror images."""

    def __init__(self, net, perm):
        super().__init__(net.config)
        self.load_state_dict(net.state_dict())
        self.perm = perm

    def forward(self, x):
        return merge_mirrored_outputs(super().forward(x), super().forward(mirror_network_input(x)),
                                      self.config.n_joints, self.perm)


def test_the_pipeline_runs_the_mirror_image_when_the_refinement_says_so():
    torch.manual_seed(0)
    model = DenseNet(DenseConfig(n_joints=2, width=4)).eval()
    cam = CameraConfig()
    depth = _box_depths(3, cam.height_px, cam.width_px)
    n = len(depth)
    data = DenseData(quantise_depth(depth), np.repeat(cam.K[None].astype(np.float32), n, 0), None, None, None, None,
                     None, None, object_index=np.arange(n), sample_id=np.arange(n), shard_of=np.zeros(n, int))
    idx = np.arange(n)
    joints = ["revolute", "revolute"]
    ref = Refinement(frame=True)
    plain = predict_arrays(model, data, idx, joint_types=joints, calibration=None, refinement=ref)
    both = predict_arrays(model, data, idx, joint_types=joints, calibration=None,
                          refinement=replace(ref, mirror_joints=(1, 0)).to_dict())
    averaged = predict_arrays(_Averaged(model, (1, 0)).eval(), data, idx, joint_types=joints, calibration=None,
                              refinement=ref)
    assert np.allclose(both["mixture_means"], averaged["mixture_means"], atol=1e-5)
    assert not np.allclose(both["axis_pose"][..., :3], plain["axis_pose"][..., :3], atol=1e-4)  # something was averaged


def test_network_outputs_average_the_mirror_images_of_a_batch_larger_than_a_chunk():
    """A batch larger than a network chunk (the network runs chunk by chunk, each image and its
    mirror image in separate calls) gives the same numbers as averaging image by image; the
    mirror input keeps a channels-last input's layout."""
    from articulated_dataset.methods.dense.predict import NETWORK_CHUNK, network_outputs

    torch.manual_seed(1)
    model = DenseNet(DenseConfig(n_joints=2, width=4)).eval()
    cam = CameraConfig()
    n = NETWORK_CHUNK + 5  # one full chunk and a partial one
    depth = torch.from_numpy(_box_depths(n, cam.height_px, cam.width_px))
    x = make_inputs(depth, torch.from_numpy(np.repeat(cam.K[None].astype(np.float32), n, 0)))["x"]
    with torch.inference_mode():
        got = network_outputs(model, x, (1, 0))
        expected = _Averaged(model, (1, 0)).eval()(x)
        channels_last = mirror_network_input(x.contiguous(memory_format=torch.channels_last))
        assert channels_last.is_contiguous(memory_format=torch.channels_last)
        assert torch.equal(channels_last, mirror_network_input(x))
    assert torch.allclose(got, expected, atol=1e-5)
    assert not torch.allclose(got, network_outputs(model, x), atol=1e-4)  # something was averaged


def test_with_mirror_drops_only_step_8():
    from articulated_dataset.methods.dense.mirror import with_mirror

    ref = Refinement(frame=True, mirror_joints=(0,))
    assert with_mirror(ref, True) == ref
    assert with_mirror(ref.to_dict(), False) == replace(ref, mirror_joints=None)
    assert with_mirror(None, False) is None
    plain = Refinement(frame=True)
    assert with_mirror(plain, False) == plain


@pytest.fixture(scope="module")
def cabinet_split(tmp_path_factory):
    return generated_split(tmp_path_factory.mktemp("nomirror"), "cabinet", 1, 5)


def _cli(*args):
    from click.testing import CliRunner

    from articulated_dataset.cli import main

    return CliRunner().invoke(main, list(args))


def test_predict_no_mirror_skips_the_mirror_image(cabinet_split, tmp_path):
    """The shipped cabinet model averages with the mirror image; --no-mirror gives the
    estimate of the image alone (the pipeline without step 8) and says so in the file."""
    from articulated_dataset.benchmark.predictions import read_predictions
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense.checkpoint import build_dense_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split

    ckpt = load_dense_checkpoint(resolve_model("dense", "cabinet").path)
    if Refinement.from_dict(ckpt["refinement"]).mirror_joints is None:
        pytest.skip("the shipped cabinet model does not use the mirror image")
    outs = {}
    for name, extra in (("with", []), ("without", ["--no-mirror"])):
        out = tmp_path / f"{name}.h5"
        r = _cli("predict", "--model", "dense", str(cabinet_split), "--out", str(out), "--threads", "1", "-q",
                 *extra)
        assert r.exit_code == 0, r.output
        attrs, arrays = read_predictions(out)
        outs[name] = arrays["cabinet"]
        assert int(attrs["mirror"]) == (name == "with")
    model = build_dense_model(ckpt)
    c = model.config
    data = load_dense_split(cabinet_split, c.n_joints, (c.height_px, c.width_px), with_labels=False)
    idx = np.arange(len(data.sample_id))
    alone = predict_arrays(model, data, idx, joint_types=list(ckpt["joint_types"]), calibration=ckpt.get("calibration"),
                           refinement=replace(Refinement.from_dict(ckpt["refinement"]), mirror_joints=None))
    assert np.allclose(outs["without"]["axis_pose"], alone["axis_pose"], atol=1e-6)
    assert np.allclose(outs["without"]["q"], alone["q"], atol=1e-6)
    assert not np.allclose(outs["with"]["axis_pose"][..., :3], alone["axis_pose"][..., :3], atol=1e-4)


def test_no_mirror_is_for_the_dense_model(cabinet_split, tmp_path):
    r = _cli("predict", "--model", "mdn-small", str(cabinet_split), "--out", str(tmp_path / "p.h5"),
             "--no-mirror", "-q")
    assert r.exit_code == 2 and r.output.strip() == "artdata: error: --no-mirror applies to the dense model"


def test_estimate_no_mirror(cabinet_split):
    """One image: articulated_dataset.estimate(mirror=False) is the image's own estimate, and the
    default averages it with the mirror image's."""
    import h5py

    import articulated_dataset as ad

    with h5py.File(sorted(cabinet_split.glob("shard-*.h5"))[0], "r") as f:
        depth, K = f["depth"][0], f["K"][()]
    both, alone = ad.estimate(depth, K, "cabinet"), ad.estimate(depth, K, "cabinet", mirror=False)
    again = ad.estimate(depth, K, "cabinet", mirror=False)
    assert np.array_equal(alone.axis_origin_m, again.axis_origin_m)
    assert not np.allclose(both.axis_origin_m, alone.axis_origin_m, atol=1e-5)
