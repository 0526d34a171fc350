"""Realistic shapes: ``generate --table realistic``.

Each built-in class has a realistic table (classes/realistic.py): its sizes are a mixture
of correlated size classes built from standard dimensions instead of the paper's independent
uniform ranges.  Checked here: the tables sample what they declare (2,000 draws per class, no
rendering), the paper's tables are untouched, realistic splits of every class (2 objects
each) have labels that explain their pixels, verify, and are seeded; the CLI records the
table and refuses unknown ones in one line.  tests/generation/test_labels.py runs its label-versus-pixel
checks with the realistic tables too.
"""

import json
import shutil
from dataclasses import replace

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.classes.registry import all_classes, get_class
from articulated_dataset.cli import main
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.tables import GEOMETRY_KEYS, SamplingTable, ShapeMixture
from articulated_dataset.format import MANIFEST_NAME, open_split, read_manifest, sha256_file
from articulated_dataset.generation import GenerationConfig, generate_split, object_sample
from articulated_dataset.generation.sampling import object_rng, sample_object
from articulated_dataset.tools.verify import verify_split
from helpers_core import IMAGE_CHECK_FIELDS, ROOT, assert_one_line_error, check_stored_images, write_flap_urdf

CLASSES = all_classes()
N_DRAWS = 2000
INCH_M = 0.0254


def _draws(obj_class, n=N_DRAWS):
    """``n`` objects' (sizes, size class) from their own streams, as the pipeline draws them."""
    table = obj_class.realistic_table
    out = [table.shape.sample(object_rng(0, obj_class.name, "train", k), table.geometry) for k in range(n)]
    sizes = np.array([[g[key] for key in GEOMETRY_KEYS] for g, _ in out])
    return sizes, np.array([c for _, c in out])


# --------------------------------------------------------------------------------------
# The distributions, sampled directly (no rendering)
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("obj_class", CLASSES, ids=lambda c: c.name)
def test_sizes_follow_the_declared_size_classes(obj_class):
    table = obj_class.realistic_table
    shape = table.shape
    sizes, comp = _draws(obj_class)
    lo = np.array([table.geometry[k][0] for k in GEOMETRY_KEYS])
    hi = np.array([table.geometry[k][1] for k in GEOMETRY_KEYS])
    assert np.all((sizes >= lo) & (sizes <= hi))
    # size classes as often as their weights (within 4 binomial sd)
    p = shape.probabilities
    counts = np.bincount(comp, minlength=len(p))
    assert np.all(np.abs(counts - N_DRAWS * p) <= 4 * np.sqrt(N_DRAWS * p * (1 - p)) + 1), (counts, N_DRAWS * p)
    for c, component in enumerate(shape.components):
        x = sizes[comp == c]
        std = np.array([component.std_m[k] for k in GEOMETRY_KEYS])
        for i, key in enumerate(GEOMETRY_KEYS):
            nominal = np.array(component.sizes_m[key])
            offset = x[:, i, None] - nominal[None, :]
            nearest = np.argmin(np.abs(offset), axis=1)
            residual = offset[np.arange(len(x)), nearest]
            # every draw is a standard size plus its jitter; every standard size is used
            assert np.all(np.abs(residual) <= 5 * std[i] + 1e-9), (component.name, key)
            if len(nominal) > 1:
                assert len(set(nearest)) == len(nominal), (component.name, key)
            if std[i] > 0 and len(x) > 100:
                assert np.std(residual) == pytest.approx(std[i], rel=0.2), (component.name, key)
        corr = np.array(component.corr)
        if len(x) > 150 and np.any(corr != np.eye(3)):  # the declared correlations, within 4 standard errors
            assert np.allclose(np.corrcoef(x, rowvar=False), corr, atol=4 / np.sqrt(len(x))), component.name
        assert all(shape.component_of(s) is not None for s in x)


def test_appliance_sizes_grow_together_and_the_paper_sizes_do_not():
    """A larger appliance is wider, taller and deeper together (over all its size classes);
    the paper's independent ranges show no such correlation (the check can fail)."""
    for name in ("microwave", "toaster", "refrigerator"):
        c = get_class(name)
        sizes, _ = _draws(c)
        r = np.corrcoef(sizes, rowvar=False)
        assert r[0, 1] > 0.3 and r[0, 2] > 0.3 and r[1, 2] > 0.3, (name, r)
        paper = np.array([[s.geometry[k] for k in GEOMETRY_KEYS] for s in
                          (sample_object(c, c.table, seed=0, split="train", object_index=k, n_images=1)[0] for k in range(N_DRAWS))])
        rp = np.corrcoef(paper, rowvar=False)
        assert np.all(np.abs(rp[np.triu_indices(3, 1)]) < 0.1), (name, rp)


def test_cabinets_take_standard_sizes():
    """Cabinet widths are 3-in steps (9-24 in with one door, 24-48 in with two); 12-in-deep
    cabinets are wall cabinets (30, 36 or 42 in tall, or 12-18 in over a refrigerator); base
    cabinets are 34.5 in tall."""
    for name, (wmin, wmax) in (("cabinet", (9, 24)), ("cabinet2", (24, 48))):
        sizes, _ = _draws(get_class(name))
        d_in, w_in, h_in = (sizes / INCH_M).T
        assert np.all(np.abs(w_in - 3 * np.round(w_in / 3)) < 0.5)
        assert wmin - 0.5 < w_in.min() and w_in.max() < wmax + 0.5
        wall = np.abs(d_in - 12) < 1.5
        assert 0.2 < wall.mean() < 0.5
        standard_heights = np.array([12, 15, 18, 30, 36, 42])
        assert np.all(np.min(np.abs(h_in[wall, None] - standard_heights), axis=1) < 0.5)
        base = np.abs(d_in - 24) < 1.5
        assert np.mean(np.abs(h_in[base] - 34.5) < 1.0) > 0.7  # the rest: tall cabinets
    sizes, _ = _draws(get_class("drawer"))
    assert sizes[:, 0].min() > get_class("drawer").table.q[0][1]  # the drawer never leaves its shell


def test_objects_draw_their_sizes_from_their_own_stream():
    c = get_class("toaster")
    for k in range(5):
        s, _ = sample_object(c, c.realistic_table, seed=3, split="val", object_index=k, n_images=4)
        g, _ = c.realistic_table.shape.sample(object_rng(3, c.name, "val", k), c.realistic_table.geometry)
        assert s.geometry == g
    # a mean object lies at the mixture's mean
    mean = object_sample(GenerationConfig("toaster", table=c.realistic_table, mean=True, n_objects=1), 0)
    assert [mean.geometry[k] for k in GEOMETRY_KEYS] == pytest.approx(c.realistic_table.shape.mean_m())


def test_paper_tables_are_unchanged_and_realistic_ones_change_only_the_sizes():
    for c in CLASSES:
        paper, real = c.named_table("paper"), c.named_table("realistic")
        assert paper is c.table and paper.shape is None and "shape" not in paper.to_dict()
        assert GenerationConfig(c.name).table.to_json() == paper.to_json()
        assert (real.pose, real.q, real.chirality_p, real.extra) == (paper.pose, paper.q, paper.chirality_p, paper.extra)
        assert real.shape is not None and real.kind == "realistic" and paper.kind == "uniform"
        assert SamplingTable.from_dict(json.loads(real.to_json())) == real  # what manifests store reads back
        assert paper.override({"shape": real.to_dict()["shape"], "geometry": real.to_dict()["geometry"]}) == real
        assert real.override({"shape": None, "geometry": paper.to_dict()["geometry"]}) == paper
    with pytest.raises(UserError, match="unknown sampling table 'huge'"):
        get_class("cabinet").named_table("huge")
    with pytest.raises(UserError, match="has no realistic table"):
        replace(get_class("cabinet"), realistic_table=None).named_table("realistic")


def _shape(**changes):
    c = get_class("microwave").realistic_table.to_dict()
    comp = {**c["shape"]["components"][0], **changes}
    return {"geometry": c["geometry"], "shape": {"components": [comp]}}


@pytest.mark.parametrize("changes, needle", [
    ({"weight": -1}, "weight"),
    ({"weight": "heavy"}, "weight must be a number"),
    ({"corr": [[1, 1, 0], [1, 1, 0], [0, 0, 1]]}, "positive definite"),
    ({"corr": [[1, 0.2, 0], [0.3, 1, 0], [0, 0, 1]]}, "symmetric"),
    ({"corr": [[1, 0], [0, 1]]}, "3x3"),
    ({"std_m": {"depth_m": 0.01, "width_m": 0.01}}, "std_m needs exactly"),
    ({"std_m": {"depth_m": 0.01, "width_m": 0.01, "height_m": -0.01}}, "std_m must lie"),
    ({"sizes_m": {"depth_m": [0.4], "width_m": [0.5], "height_m": [0.9]}}, "sizes_m.height_m must lie within geometry"),
    ({"sizes_m": {"depth_m": [], "width_m": [0.5], "height_m": [0.3]}}, "list of 1-64"),
    ({"name": "x" * 80}, "name"),
    ({"colour": "red"}, "unknown colour"),
])
def test_malformed_shapes_are_one_user_error_naming_the_key(changes, needle):
    paper = get_class("microwave").table
    with pytest.raises(UserError, match=needle):
        paper.override(_shape(**changes))
    with pytest.raises(UserError, match="1-64 components"):
        ShapeMixture([])


# --------------------------------------------------------------------------------------
# Generated realistic splits: labels against pixels, verify, seeding
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def realistic_root(tmp_path_factory):
    """``root/<class>/train``: 2 objects x 16 images of every class with its realistic table."""
    root = tmp_path_factory.mktemp("realistic")
    for c in CLASSES:
        generate_split(GenerationConfig(c.name, n_objects=2, objects_per_shard=2, table=c.realistic_table), root)
    return root


@pytest.mark.parametrize("obj_class", CLASSES, ids=lambda c: c.name)
def test_realistic_labels_explain_every_image(realistic_root, obj_class):
    """In every image: body pixels lie in the object's box (object_pose, geometry); each
    moving part's pixels, moved back by -q about the labelled axis, lie in the closed
    object's box (+ handle); not moving them back fails for parts open >= 30%.  The geometry
    labels are the objects' sampled sizes, each in a size class of the table."""
    split = realistic_root / obj_class.name / "train"
    manifest, shards = open_split(split)
    config = GenerationConfig.from_dict(manifest["config"])
    assert config.table == obj_class.realistic_table
    K = np.asarray(shards[0].K)
    detected = checked = n_body = 0
    for sh in shards:
        a = {k: sh.read(k) for k in (*IMAGE_CHECK_FIELDS, "object_index")}
        sh.close()
        for k in np.unique(a["object_index"]):
            sizes = a["geometry"][a["object_index"] == k, :3].astype(np.float64)
            want = object_sample(config, int(k)).geometry
            assert np.allclose(sizes, [want[key] for key in GEOMETRY_KEYS], atol=1e-6)
            assert config.table.shape.component_of(sizes[0], tol_m=1e-6) is not None
        counts = check_stored_images(obj_class, a, K)
        checked, detected, n_body = checked + counts[0], detected + counts[1], n_body + counts[2]
    assert checked > 0 and detected >= 0.9 * checked and n_body > 1000


def test_realistic_splits_verify_record_the_table_and_verify_checks_the_sizes(realistic_root, tmp_path):
    for c in CLASSES:
        split = realistic_root / c.name / "train"
        report = verify_split(split)
        assert report.ok, report.problems
        _, shards = open_split(split)
        stored = shards[0].attrs["sampling_table"]
        shards[0].close()
        assert json.loads(stored)["shape"] == c.realistic_table.to_dict()["shape"]
        assert read_manifest(split)["config"]["table"] == c.realistic_table.to_dict()
    info = CliRunner().invoke(main, ["info", str(realistic_root / "cabinet" / "train")])
    assert info.exit_code == 0 and "table realistic: 4 size classes (base, 1 door; wall, 1 door;" in info.output
    # a size no size class explains (an 0.45 m deep cabinet: between wall, vanity and base depths)
    damaged = tmp_path / "cabinet" / "train"
    shutil.copytree(realistic_root / "cabinet" / "train", damaged)
    shard = read_manifest(damaged)["shards"][0]
    with h5py.File(damaged / shard["file"], "r+") as f:
        g = f["geometry"][()]
        g[16:, 0] = 0.45
        f["geometry"][...] = g
    m = json.loads((damaged / MANIFEST_NAME).read_text())
    m["shards"][0]["bytes"], m["shards"][0]["sha256"] = (damaged / shard["file"]).stat().st_size, sha256_file(damaged / shard["file"])
    (damaged / MANIFEST_NAME).write_text(json.dumps(m))
    report = verify_split(damaged)
    assert not report.ok
    assert any("no size class of the table explains" in str(p) and "first: image 16" in str(p) for p in report.problems)


@pytest.mark.slow
def test_realistic_bytes_are_seeded_and_independent_of_workers(tmp_path):
    def run(out, *extra):
        r = CliRunner().invoke(main, ["generate", "--class", "cabinet2", "--table", "realistic", "--n", "3", "--images", "2",
                                      "--objects-per-shard", "1", "--out", str(out), "-q", *extra])
        assert r.exit_code == 0, r.output
        return [s["sha256"] for s in read_manifest(out / "cabinet2" / "train")["shards"]]

    one = run(tmp_path / "a", "--workers", "1")
    assert run(tmp_path / "b", "--workers", "2") == one
    assert run(tmp_path / "c", "--workers", "1") == one
    assert run(tmp_path / "d", "--workers", "1", "--seed", "5") != one


# --------------------------------------------------------------------------------------
# CLI
# --------------------------------------------------------------------------------------

def test_cli_records_the_table_and_combines_it_with_a_file(tmp_path):
    override = tmp_path / "mirror.json"
    override.write_text('{"chirality_p": 1.0}')
    r = CliRunner().invoke(main, ["generate", "--class", "cabinet", "--table", "realistic", "--table", str(override),
                                  "--n", "1", "--images", "2", "--out", str(tmp_path / "out"), "-q", "--workers", "1"])
    assert r.exit_code == 0, r.output
    split = tmp_path / "out" / "cabinet" / "train"
    table = SamplingTable.from_dict(read_manifest(split)["config"]["table"])
    assert table == get_class("cabinet").realistic_table.override({"chirality_p": 1.0})
    _, shards = open_split(split)
    assert shards[0].read("geometry")[0, 3] == 1 and json.loads(shards[0].attrs["sampling_table"])["chirality_p"] == 1.0
    shards[0].close()
    r = CliRunner().invoke(main, ["generate", "--class", "cabinet", "--table", "paper", "--n", "1", "--images", "2",
                                  "--out", str(tmp_path / "paper"), "-q", "--workers", "1"])
    assert r.exit_code == 0, r.output
    assert read_manifest(tmp_path / "paper" / "cabinet" / "train")["config"]["table"] == get_class("cabinet").table.to_dict()


@pytest.mark.parametrize("args, needle", [
    (["--table", "realistc"], "unknown sampling table 'realistc'; choose from: paper, realistic"),
    (["--table", "realistic", "--table", "paper"], "give one table name"),
    (["--table", "missing.toml"], "not found"),
])
def test_cli_refuses_bad_tables_in_one_line(tmp_path, args, needle):
    r = CliRunner().invoke(main, ["generate", "--class", "drawer", "--n", "1", "--out", str(tmp_path), "-q", *args])
    assert_one_line_error(r, needle)
    assert not any(tmp_path.iterdir())


def test_docs_show_every_realistic_table():
    """docs/generation.md holds each table as ``python -m articulated_dataset.classes.realistic``
    prints it (a changed table must change the docs)."""

    from articulated_dataset.classes.realistic import markdown_table

    text = (ROOT / "docs" / "generation.md").read_text()
    for c in CLASSES:
        assert f"**{c.name}**\n\n{markdown_table(c.realistic_table)}\n" in text, c.name


@pytest.mark.slow
def test_datasheet_figures_are_the_tables_own():
    """DATASHEET.md's size percentiles and correlations are reproduced by 10,000 draws."""

    text = (ROOT / "DATASHEET.md").read_text()
    for c in CLASSES:
        x, _ = _draws(c, 10_000)
        p1, p50, p99 = np.percentile(x, [1, 50, 99], axis=0)
        r = np.corrcoef(x, rowvar=False)
        cells = " | ".join(f"{a:.2f}-{b:.2f} ({m:.2f})" for a, b, m in zip(p1, p99, p50))
        row = f"{cells} | {r[0, 1]:+.2f} / {r[0, 2]:+.2f} / {r[1, 2]:+.2f} |"
        assert f"| {c.name} | {len(c.realistic_table.shape.components)} (" in text and row in text, (c.name, row)


def test_a_realistic_mean_object_verifies(tmp_path):
    """``--mean --table realistic``: the mixture's mean sizes (a cabinet between its size
    classes), which verify checks as the mean rather than against the size classes."""
    c = get_class("cabinet")
    split = generate_split(GenerationConfig("cabinet", split="mean", n_objects=1, mean=True, table=c.realistic_table), tmp_path)
    assert verify_split(split).ok
    _, shards = open_split(split)
    g = shards[0].read("geometry")[:, :3].astype(np.float64)
    shards[0].close()
    assert np.allclose(g, c.realistic_table.shape.mean_m(), atol=1e-6)
    assert c.realistic_table.shape.component_of(g[0]) is None  # no size class explains it


def test_a_third_party_class_has_no_realistic_table(tmp_path):
    urdf = write_flap_urdf(tmp_path)
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["generate", "--urdf", str(urdf), "--class-name", "flap", "--table", "realistic", "--n", "1",
                                  "--out", str(out), "-q"])
    lines = [x for x in r.output.strip().splitlines() if x.strip()]
    assert r.exit_code == 2 and len(lines) == 1 and "has no realistic table" in lines[0], r.output
    assert not out.exists()
