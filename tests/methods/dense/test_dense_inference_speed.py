"""What makes dense inference fast, checked for keeping its numbers: the folded network
(DenseNet.folded), predict's worker processes (predict_arrays(workers=...), artdata predict
--workers) and the allocator setting of the commands (executors.configure_allocator)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from articulated_dataset.core import pool as E
from articulated_dataset.methods.dense import predict as P
from articulated_dataset.methods.dense.model import DenseConfig, DenseNet  # noqa: E402
from helpers_core import ROOT, generated_split  # noqa: E402


def _random_statistics(model: DenseNet) -> DenseNet:
    """Batch normalisations with statistics and affine weights far from the identity."""
    g = torch.Generator().manual_seed(0)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(torch.randn(m.num_features, generator=g))
            m.running_var.copy_(torch.rand(m.num_features, generator=g) * 2 + 0.1)
            m.weight.data.copy_(torch.randn(m.num_features, generator=g))
            m.bias.data.copy_(torch.randn(m.num_features, generator=g))
    return model


def test_the_folded_network_computes_the_same_function():
    model = _random_statistics(DenseNet(DenseConfig(n_joints=2, width=8))).eval()
    folded = model.folded()
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())  # the original is left as it was
    assert not folded.training and folded.config == model.config
    x = torch.randn(3, 9, 108, 192, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        a, b = model(x), folded(x)
    assert a.shape == b.shape
    assert (a - b).abs().max().item() <= 1e-4 * max(1.0, a.abs().max().item())


def test_the_inference_copy_prepacks_its_convolutions_and_computes_the_same_function():
    """On a CPU build with oneDNN, folded() computes every convolution (and the ReLU after it) with
    weights reordered once (PackedConv2d): the unpacked folded function to float rounding, on any
    batch size and after the input's size changes; pickled (to a prediction worker) without the
    opaque packed weights, which the copy makes again."""
    import pickle

    from articulated_dataset.methods.dense import model as M

    if not M._mkldnn_packing_available():
        pytest.skip("this PyTorch has no oneDNN convolution with prepacked weights")
    model = _random_statistics(DenseNet(DenseConfig(n_joints=2, width=8))).eval()
    packed = model.folded()
    convs = [m for m in packed.modules() if isinstance(m, (torch.nn.Conv2d, M.PackedConv2d))]
    assert convs and all(isinstance(m, M.PackedConv2d) for m in convs)
    assert sum(m.relu for m in convs) == sum(isinstance(m, torch.nn.ReLU) for m in model.modules()
                                             if m is not model.context[1])  # every ReLU after a convolution fused
    assert not any(isinstance(m, torch.nn.ReLU) for m in packed.modules() if m is not packed.context[1])
    g = torch.Generator().manual_seed(3)
    with torch.inference_mode():
        for shape in ((3, 9, 108, 192), (1, 9, 108, 192), (2, 9, 64, 96)):
            x = torch.randn(*shape, generator=g)
            a, b = model(x), packed(x)
            assert a.shape == b.shape and b.is_contiguous()
            assert (a - b).abs().max().item() <= 1e-4 * max(1.0, a.abs().max().item()), shape
        assert convs[0]._packed is not None
        copy = pickle.loads(pickle.dumps(packed))
        assert all(m._packed is None for m in copy.modules() if isinstance(m, M.PackedConv2d))
        assert torch.equal(copy(x), packed(x))
    assert not any(isinstance(m, M.PackedConv2d) for m in model.folded("bfloat16").modules())


def test_a_convolution_oneDNN_cannot_prepack_runs_unpacked(monkeypatch, caplog):
    """Prepacking refused at run time (another CPU, a shape oneDNN declines): the plain
    convolution, the same function, and a warning."""
    from articulated_dataset.methods.dense import model as M

    if not M._mkldnn_packing_available():
        pytest.skip("this PyTorch has no oneDNN convolution with prepacked weights")
    model = _random_statistics(DenseNet(DenseConfig(n_joints=1, width=4))).eval()
    packed = model.folded()

    def refuse(*args, **kwargs):
        raise RuntimeError("no kernel for this CPU")

    monkeypatch.setattr(torch.ops.mkldnn, "_reorder_convolution_weight", refuse)
    monkeypatch.setattr(M, "_PACKING_WARNED", [])
    x = torch.randn(2, 9, 108, 192, generator=torch.Generator().manual_seed(4))
    with torch.inference_mode(), caplog.at_level("WARNING"):
        a, b = model(x), packed(x)
    assert (a - b).abs().max().item() <= 1e-4 * max(1.0, a.abs().max().item())
    assert caplog.text.count("prepacking failed") == 1  # once, not once per convolution


def test_folding_a_training_model_uses_its_running_statistics():
    """folded() is the eval-mode function even of a model in training mode (whose batch
    normalisation would use the batch's statistics)."""
    model = _random_statistics(DenseNet(DenseConfig(n_joints=1, width=4))).train()
    folded = model.folded()
    assert model.training  # not switched by folding
    x = torch.randn(2, 9, 108, 192, generator=torch.Generator().manual_seed(2))
    with torch.inference_mode():
        expected = model.eval()(x)
        assert torch.allclose(folded(x), expected, atol=1e-4, rtol=1e-4)


def test_default_workers(monkeypatch):
    assert P.default_workers(P.PARALLEL_MIN_IMAGES - 1) == 1
    monkeypatch.setattr(E, "usable_cpus", lambda: 4)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert P.default_workers(P.PARALLEL_MIN_IMAGES) == 2
        torch.set_num_threads(1)
        assert P.default_workers(10 ** 6) == 1  # --threads 1: this process alone
    finally:
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def cabinet_split(tmp_path_factory):
    return generated_split(tmp_path_factory.mktemp("workers"), "cabinet", 3, 8)


@pytest.mark.slow
def test_worker_processes_give_the_same_predictions(cabinet_split, monkeypatch):
    """The shipped cabinet model (refinement with the mirror image and the handles) over three
    tasks in two spawned processes: the same images in the same order, the same numbers."""
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split

    ckpt = load_dense_checkpoint(resolve_model("dense", "cabinet").path)
    model = build_inference_model(ckpt)
    c = model.config
    data = load_dense_split(cabinet_split, c.n_joints, (c.height_px, c.width_px), with_labels=False)
    idx = np.arange(len(data.sample_id))[::-1].copy()  # not the split's order
    kw = dict(joint_types=list(ckpt["joint_types"]), calibration=ckpt.get("calibration"),
              refinement=ckpt.get("refinement"), batch_size=8)
    alone = P.predict_arrays(model, data, idx, **kw)
    monkeypatch.setattr(P, "WORKER_TASK_IMAGES", 16)  # 48 images: three tasks
    shared = P.predict_arrays(model, data, idx, workers=2, **kw)
    assert set(shared) == set(alone)
    assert np.array_equal(shared["sample_id"], data.sample_id[idx])
    for k, v in alone.items():
        if not isinstance(v, np.ndarray):  # the mixture's layout (column names)
            assert shared[k] == v, k
            continue
        assert shared[k].shape == v.shape, k
        assert np.allclose(shared[k], v, atol=1e-6, rtol=0), k


def _cli(*args):
    from click.testing import CliRunner

    from articulated_dataset.cli import main

    return CliRunner().invoke(main, list(args))


@pytest.mark.slow
def test_predict_workers_on_the_command_line(cabinet_split, tmp_path):
    from articulated_dataset.benchmark.predictions import read_predictions

    outs = {}
    for w in ("1", "2"):
        out = tmp_path / f"w{w}.h5"
        r = _cli("predict", "--model", "dense", str(cabinet_split), "--out", str(out), "--workers", w,
                 "--batch-size", "16", "-q")
        assert r.exit_code == 0, r.output
        outs[w] = read_predictions(out)[1]["cabinet"]
    for k in ("axis_pose", "q", "mixture_weights"):
        assert np.allclose(outs["1"][k], outs["2"][k], atol=1e-6), k


@pytest.mark.parametrize("model, workers, message", [
    ("dense", "0", "artdata: error: --workers must be positive, got 0"),
    ("dense", str(4 * (os.cpu_count() or 1) + 1),
     f"artdata: error: --workers {4 * (os.cpu_count() or 1) + 1} is more than 4 per logical CPU of this machine "
     f"(at most {4 * (os.cpu_count() or 1)})"),
    ("mdn-small", "2", "artdata: error: --workers applies to the dense model (the MDN uses torch's threads)"),
])
def test_predict_workers_errors(cabinet_split, tmp_path, model, workers, message):
    r = _cli("predict", "--model", model, str(cabinet_split), "--out", str(tmp_path / "p.h5"),
             "--workers", workers, "-q")
    assert r.exit_code == 2 and r.output.strip() == message


#: Allocates a 200 MB block and prints glibc's counts (mallinfo2) while it is held and after it
#: is freed: bytes in mapped blocks (hblkhd) and the heap's free bytes (fordblks).
MALLINFO = """
import ctypes, json
from articulated_dataset.core.pool import configure_allocator
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Info
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
chosen = configure_allocator() if CONFIGURE else None
block = libc.malloc(200_000_000)
held = libc.mallinfo2()
libc.free(block)
freed = libc.mallinfo2()
print(json.dumps({"chosen": chosen, "mapped_held": held.hblkhd, "heap_free_after": freed.fordblks}))
"""
BLOCK_BYTES = 200_000_000


def _mallinfo(configure: bool, **env) -> dict:
    base = {k: v for k, v in os.environ.items() if k not in E.ALLOCATOR_VARIABLES}
    out = subprocess.run([sys.executable, "-c", f"CONFIGURE = {configure}\n" + MALLINFO], env={**base, **env},
                         capture_output=True, text=True)
    if out.returncode and "mallinfo2" in out.stderr:
        pytest.skip("no mallinfo2 in this C library (glibc < 2.33)")
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_the_allocator_setting_reuses_freed_memory():
    """By default a 200 MB block is mapped for itself and unmapped when freed (its pages fresh
    every time); set, it comes from the heap and stays there, free, for the next one."""
    default, kept = _mallinfo(False), _mallinfo(True)
    assert default["chosen"] is None and kept["chosen"] is True
    assert default["mapped_held"] >= BLOCK_BYTES and default["heap_free_after"] < BLOCK_BYTES
    # (blocks mapped before it was set stay mapped)
    assert kept["mapped_held"] < BLOCK_BYTES and kept["heap_free_after"] >= BLOCK_BYTES


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_users_allocator_setting_is_kept():
    r = _mallinfo(True, MALLOC_TRIM_THRESHOLD_="131072")
    assert r["chosen"] is False and r["mapped_held"] >= BLOCK_BYTES


def test_the_bfloat16_network_rounds_the_float32_one():
    """folded(precision="bfloat16"): every weight in bfloat16, float32 in and out, outputs near the
    float32 copy's (bfloat16 keeps 8 significant bits) but not equal to them (it is really used)."""
    model = _random_statistics(DenseNet(DenseConfig(n_joints=1, width=8))).eval()
    fp32, bf16 = model.folded(), model.folded("bfloat16")
    assert {p.dtype for p in bf16.parameters()} == {torch.bfloat16}
    assert {p.dtype for p in fp32.parameters()} == {torch.float32}
    x = torch.randn(2, 9, 108, 192, generator=torch.Generator().manual_seed(3))
    with torch.inference_mode():
        a, b = fp32(x), bf16(x)
    assert b.dtype == torch.float32 and b.shape == a.shape and b.is_contiguous()
    scale = a.abs().max().item()
    assert 0 < (a - b).abs().max().item() <= 0.1 * scale
    assert (a - b).abs().mean().item() <= 0.01 * scale
    with pytest.raises(ValueError, match="precision"):
        model.folded("float16")


def test_bfloat16_predictions_are_near_float32s(cabinet_split):
    """The shipped cabinet model in both precisions on a rendered split: the same hinge sides and
    axes within a few millimetres and tenths of a degree for nearly every image."""
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split

    ckpt = load_dense_checkpoint(resolve_model("dense", "cabinet").path)
    out = {}
    for precision in ("float32", "bfloat16"):
        model = build_inference_model(ckpt, precision)
        c = model.config
        data = load_dense_split(cabinet_split, c.n_joints, (c.height_px, c.width_px), with_labels=False)
        out[precision] = P.predict_arrays(model, data, np.arange(len(data.sample_id)), joint_types=list(ckpt["joint_types"]),
                                          calibration=ckpt.get("calibration"), refinement=ckpt.get("refinement"))
    a, b = out["float32"]["axis_pose"], out["bfloat16"]["axis_pose"]
    moved_cm = 100 * np.linalg.norm(a[..., :3] - b[..., :3], axis=-1)
    assert np.median(moved_cm) < 0.5 and np.mean(moved_cm < 2.0) >= 0.9
    dq_deg = np.degrees(np.abs(out["float32"]["q"] - out["bfloat16"]["q"]))
    assert np.median(dq_deg) < 0.5


#: A handle-height gate (m) that turns refinement step 9 on.
HANDLE_HEIGHT_GATE_M = 0.2


def test_only_the_door_angles_a_refinement_reads_are_computed(cabinet_split):
    """Refinement.door_angles names what apply_refinement and the handles' choice of doors read;
    refined_quantities with that subset gives those keys with the numbers of the full computation."""
    from dataclasses import replace

    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense import refine as R
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split

    ckpt = load_dense_checkpoint(resolve_model("dense", "cabinet").path)
    # the shipped cabinet's refinement with steps 7 and 9 both on (its fit may switch step 9 off)
    ref = replace(R.as_refinement(ckpt["refinement"]), handle_height_gate_m=HANDLE_HEIGHT_GATE_M)
    assert ref.door_angle_signed and ref.handle_max_q_deg is not None and ref.handle_height_gate_m is not None
    assert ref.door_angles == ("q_signed",)  # step 9 measures every door's handle
    # step 7 alone measures the handles of the doors whose plain angle may be below its limit
    assert replace(ref, handle_height_gate_m=None).door_angles == ("q", "q_signed")
    assert replace(ref, handle_max_q_deg=None, handle_height_gate_m=None).door_angles == ("q_signed",)
    assert replace(ref, door_angle_signed=False, door_angle_folded=True, handle_max_q_deg=None).door_angles == ("q_folded",)
    assert replace(ref, min_door_px=None, handle_max_q_deg=None).door_angles == ()
    model = build_inference_model(ckpt)
    c = model.config
    data = load_dense_split(cabinet_split, c.n_joints, (c.height_px, c.width_px), with_labels=False)
    kw = dict(joint_types=list(ckpt["joint_types"]), refine=True, split_factor=ref.split_factor,
              frame_min_prob=ref.frame_min_prob, mirror_joints=ref.mirror_joints)
    depth, K = data.depth(np.arange(16)), torch.from_numpy(data.K[:16])
    _, full = P.batch_modes(model, depth, K, **kw)
    assert set(R.DOOR_ANGLES) <= set(full)
    for angles in [("q_signed",), ("q_folded",), ()]:
        _, some = P.batch_modes(model, depth, K, door_angles=angles, **kw)
        assert set(some) == set(full) - (set(R.DOOR_ANGLES) - set(angles))
        for k, v in some.items():
            assert np.array_equal(v, full[k], equal_nan=True), k


def test_predict_and_estimate_precision_on_the_command_line(cabinet_split, tmp_path):
    from articulated_dataset.benchmark.predictions import read_predictions

    out = tmp_path / "bf16.h5"
    r = _cli("predict", "--model", "dense", str(cabinet_split), "--out", str(out), "--precision", "bfloat16",
             "--workers", "1", "-q")
    assert r.exit_code == 0, r.output
    attrs, per_class = read_predictions(out)
    assert attrs["precision"] == "bfloat16" and per_class["cabinet"]["axis_pose"].shape[0] == 48
    r = _cli("predict", "--model", "dense", str(cabinet_split), "--out", str(tmp_path / "x.h5"),
             "--precision", "float16", "-q")
    assert r.exit_code == 2 and "float16" in r.output
    r = _cli("predict", "--model", "mdn-small", str(cabinet_split), "--out", str(tmp_path / "m.h5"),
             "--precision", "bfloat16", "-q")
    assert r.exit_code == 2
    assert r.output.strip() == "artdata: error: --precision applies to the dense model (the MDN uses bfloat16 on a GPU by itself)"


def test_estimate_in_bfloat16(cabinet_split):
    import h5py

    import articulated_dataset as ad
    from articulated_dataset.core.errors import UserError

    with h5py.File(next(cabinet_split.glob("shard-*.h5")), "r") as f:
        depth, K = f["depth"][0], f["K"][()]  # metres
    K = K[0] if K.ndim == 3 else K
    a = ad.estimate(depth, K, "cabinet")
    b = ad.estimate(depth, K, "cabinet", precision="bfloat16")
    assert np.linalg.norm(a.axis_origin_m - b.axis_origin_m) < 0.05
    with pytest.raises(UserError, match="precision must be one of float32, bfloat16"):
        ad.estimate(depth, K, "cabinet", precision="half")


@pytest.mark.parametrize("max_q_deg", [None, 5.0])
def test_the_refinements_handles_are_handle_evidences(cabinet_split, max_q_deg):
    """The handles the refinement measures on the door pixels it has gathered
    (refined_quantities(handle_max_q_deg=...), as batch_modes asks for them) are handle_evidence's of the
    same doors, from the whole input: every door's (step 9) and only the candidates' (step 7
    alone), to float rounding; and enough doors have a handle for the check to mean something."""
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense import refine as R
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.handle import EVERY_DOOR_DEG, HANDLE_KEYS, handle_candidates_evidence

    ckpt = load_dense_checkpoint(resolve_model("dense", "cabinet").path)
    ref = R.as_refinement(ckpt["refinement"])
    model = build_inference_model(ckpt)
    c = model.config
    data = load_dense_split(cabinet_split, c.n_joints, (c.height_px, c.width_px), with_labels=False)
    depth, K = data.depth(np.arange(24)), torch.from_numpy(data.K[:24])
    joint_types = list(ckpt["joint_types"])
    limit = EVERY_DOOR_DEG if max_q_deg is None else max_q_deg
    _, got = P.batch_modes(model, depth, K, joint_types=joint_types, refine=True, split_factor=ref.split_factor,
                           handle_max_q_deg=limit, frame_min_prob=ref.frame_min_prob)
    with torch.inference_mode():
        from articulated_dataset.methods.dense.aggregate import vote_modes
        from articulated_dataset.methods.dense.features import make_inputs

        inputs = make_inputs(depth, K)
        parts = model.split(model(inputs["x"]))
        modes = vote_modes(parts, inputs["points_out"], inputs["weight_out"] > 0, split_factor=ref.split_factor)
        r = R.refined_quantities(parts, inputs, modes, joint_types, ref.frame_min_prob)
        want = handle_candidates_evidence(parts, inputs, modes, r, joint_types, limit)
    seen = want["handle_px"].numpy() > 0
    assert seen.sum() >= (8 if max_q_deg is None else 1), seen.sum()
    if max_q_deg is not None:
        assert not seen.all()  # some doors are not candidates (their handles are not measured)
    for k in HANDLE_KEYS:
        np.testing.assert_allclose(got[k], want[k].numpy().astype(np.float64), rtol=1e-5, atol=1e-5, err_msg=k)


def test_refinement_candidates_share_one_network_pass(cabinet_split):
    """fit_inference's candidate refinements (predict.predict_candidates): each candidate refinement gets what it
    gets alone (predict_modes), from one network pass; and the body's strip refined on the images
    whose box-frame pixels may make one (refine.strip_sized) alone, the others keeping the pair's
    quantities, is the strip refined on every image, to float rounding."""
    from articulated_dataset.methods import resolve_model
    from articulated_dataset.methods.dense.checkpoint import build_inference_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.handle import EVERY_DOOR_DEG
    from articulated_dataset.methods.dense.refine import strip_sized

    ckpt = load_dense_checkpoint(resolve_model("dense", "cabinet").path)
    model = build_inference_model(ckpt)
    c = model.config
    data = load_dense_split(cabinet_split, c.n_joints, (c.height_px, c.width_px), with_labels=False)
    idx = np.arange(len(data.sample_id))
    common = dict(joint_types=list(ckpt["joint_types"]), split_factor=ckpt["refinement"]["split_factor"], batch_size=16)

    def keywords(p, one_sided, strip=None):
        return dict(handle_max_q_deg=EVERY_DOOR_DEG, frame_min_prob=p, frame_one_sided=one_sided,
                    frame_strip_elongation=strip)

    pairs = {"all": (None, False), "sure, one-sided": (0.9, True)}
    m, rs = P.predict_candidates(model, data, idx, candidates={k: P.refinement_keywords(**keywords(*v))
                                                                for k, v in pairs.items()}, **common)
    for name, pair in pairs.items():
        m_alone, r_alone = P.predict_modes(model, data, idx, **keywords(*pair), **common)
        assert set(r_alone) == set(rs[name]) and set(m_alone) == set(m)
        for k in m:
            assert np.array_equal(m[k], m_alone[k], equal_nan=True), k
        for k in r_alone:
            assert np.array_equal(rs[name][k], r_alone[k], equal_nan=True), (name, k)
    assert not np.allclose(rs["all"]["box_x"], rs["sure, one-sided"]["box_x"], atol=1e-4)  # they differ
    pair = rs["sure, one-sided"]
    rows = np.flatnonzero(strip_sized(pair["frame_px"]))
    assert 0 < len(rows) < len(idx)
    _, some = P.predict_candidates(model, data, idx[rows], candidates={
        1.0: P.refinement_keywords(**keywords(0.9, True, 1.0))}, **common)
    _, every = P.predict_modes(model, data, idx, **keywords(0.9, True, 1.0), **common)
    merged = P._with_rows(pair, rows, some[1.0])
    # (elongation 1: every strip-sized image's pixels read as a line, so the strip turns their frames)
    assert not np.allclose(every["box_x"][rows], pair["box_x"][rows], atol=1e-3)
    for k in every:
        assert np.allclose(merged[k], every[k], atol=1e-5, rtol=0, equal_nan=True), k


def test_the_fit_benchmark_reports_its_time_and_choice(tmp_path, capsys):
    """benchmarks/fit_inference.py (the fit's time per class in docs/dense.md) runs and
    prints each class's seconds, images and the refinement chosen."""

    from helpers_core import load_script

    bench = load_script(ROOT / "benchmarks" / "fit_inference.py", "fit_inference_bench")
    threads = torch.get_num_threads()
    try:
        assert bench.main(["--class", "toaster", "--objects", "2", "--root", str(tmp_path)]) == 0
    finally:
        torch.set_num_threads(threads)  # the benchmark sets its own
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith("toaster: ") and " s for 32 images on 1 thread(s); refinement chosen: {" in line
    assert json.loads(line.split("refinement chosen: ", 1)[1])["version"] > 0


def test_the_training_runs_inference_copy_is_the_cpu_packed_folded_network():
    """train.inference_copy (the per-epoch validation's and the fit's network): the folded function
    on the CPU, prepacked where oneDNN can, the training network left as it was."""
    from articulated_dataset.methods.dense import model as M
    from articulated_dataset.methods.dense.train import inference_copy

    model = _random_statistics(DenseNet(DenseConfig(n_joints=1, width=4))).train()
    copy = inference_copy(model)
    assert model.training and not copy.training
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
    shared = {t.data_ptr() for t in model.state_dict().values()} & {t.data_ptr() for t in copy.state_dict().values()}
    assert not shared  # a copy: training on never changes it
    assert any(isinstance(m, M.PackedConv2d) for m in copy.modules()) == M._mkldnn_packing_available()
    x = torch.randn(2, 9, 108, 192, generator=torch.Generator().manual_seed(5))
    with torch.inference_mode():
        assert torch.allclose(copy(x), model.eval()(x), atol=1e-4, rtol=1e-4)
