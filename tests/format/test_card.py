"""``artdata card``: the Hugging Face dataset card that ``datasets.load_dataset`` reads the shards
through, and the Croissant metadata that ``mlcroissant`` validates (mlcroissant reads no HDF5, so
its records are not iterated: the test checks its metadata and files instead)."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.format import FIELDS, Split
from articulated_dataset.format.card import CARD_NAME, CROISSANT_NAME, RAI_SOURCES
from articulated_dataset.format.schema import OPTIONAL_FIELDS, RGB_FIELDS
from helpers_core import ROOT, assert_one_line_error
from helpers_real import write_capture

#: Croissant RAI properties a NeurIPS datasets-track submission is asked for (JSON-LD names).
RAI_KEYS = ("rai:dataCollection", "rai:dataBiases", "rai:personalSensitiveInformation", "rai:dataUseCases",
            "rai:dataLimitations", "rai:dataCollectionMissingData", "rai:dataPreprocessingProtocol",
            "rai:dataAnnotationProtocol", "rai:dataReleaseMaintenancePlan")


def artdata(*args: str):
    return CliRunner().invoke(main, [str(a) for a in args])


#: The splits of :func:`data_root`: (class, split, objects, options); 2 images per object.  The
#: microwave's colour images and occlusion fields (formats 1.1, 1.2) are 3-D and optional fields.
SPLITS = (("drawer", "train", 2, ()), ("drawer", "test", 1, ()), ("cabinet2", "train", 1, ()),
          ("microwave", "train", 1, ("--rgb", "--occluders", 1)))


@pytest.fixture(scope="module")
def data_root(tmp_path_factory) -> Path:
    """``root/<class>/<split>`` of :data:`SPLITS`."""
    root = tmp_path_factory.mktemp("card") / "data"
    for cls, split, n, options in SPLITS:
        res = artdata("generate", "--class", cls, "--split", split, "--n", n, "--images", 2, "--workers", 1,
                      *options, "--out", root, "-q")
        assert res.exit_code == 0, res.output
    return root


@pytest.fixture
def offline(monkeypatch, tmp_path):
    """``datasets`` with no network and its cache in ``tmp_path``; the module."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    import datasets
    import huggingface_hub.constants

    monkeypatch.setattr(datasets.config, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    return datasets


def card_copy(data_root: Path, dest: Path) -> Path:
    """A copy of the data root (each test writes its own card)."""
    return Path(shutil.copytree(data_root, dest))


def assert_loads_as_our_reader(datasets, card_folder: Path, config: str, split_dir: Path, cache: Path) -> None:
    """``load_dataset(card_folder, config, split=...)`` gives every stored field of ``split_dir``
    exactly as :meth:`Split.read_fields` reads it (storage order; NaN where a real capture has no label)."""
    ds = datasets.load_dataset(str(card_folder), config, split=split_dir.name, cache_dir=str(cache))
    with Split(split_dir) as split:
        names = [f.name for f in FIELDS + OPTIONAL_FIELDS + RGB_FIELDS if f.name in split.shards[0].file]
    assert sorted(ds.column_names) == sorted(names)  # the per-image fields; K and R are file-level
    got = ds.with_format("numpy")[:]  # integers as int64, floats as float32 (datasets' numpy format)
    want = Split(split_dir).read_fields(names)
    for name in names:
        expected = want[name].astype(str) if want[name].dtype.kind == "S" else want[name]
        feature = ds.features[name]
        stored = getattr(feature, "dtype", None) or feature.feature.dtype  # Value, ArrayND or List
        assert stored == ("string" if want[name].dtype.kind == "S" else str(want[name].dtype)), name
        assert got[name].shape == expected.shape, name
        np.testing.assert_array_equal(got[name], expected, err_msg=name)


def test_card_of_a_data_root_loads_with_datasets(data_root, tmp_path, offline):
    root = card_copy(data_root, tmp_path / "data")
    res = artdata("card", root)
    assert res.exit_code == 0, res.output
    text = (root / CARD_NAME).read_text()
    header = yaml.safe_load(text.split("---\n", 2)[1])
    assert header["license"] == "mit" and "robotics" in header["task_categories"]
    assert header["size_categories"] == ["n<1K"]
    configs = {c["config_name"]: c for c in header["configs"]}
    assert set(configs) == {"drawer", "cabinet2", "microwave"}
    assert {d["split"]: d["path"] for d in configs["drawer"]["data_files"]} == {
        "train": ["drawer/train/shard-00000.h5"], "test": ["drawer/test/shard-00000.h5"]}
    for config, split, *_ in SPLITS:
        assert_loads_as_our_reader(offline, root, config, root / config / split, tmp_path / "cache")
    assert "rgb" in {f["name"] for c in header["dataset_info"] if c["config_name"] == "microwave" for f in c["features"]}
    # the datasheet, the schema's words and the citation are in the card
    assert "### Known limitations" in text and "Learning to Generalize Kinematic Models to Novel Objects" in text
    for f in FIELDS:
        assert f.description.replace("|", "\\|") in text, f.name


def test_card_written_elsewhere_points_at_the_split(data_root, tmp_path, offline):
    """``--out``: the card's data paths are relative to the folder it is written to."""
    split_dir = card_copy(data_root, tmp_path / "data") / "drawer" / "train"
    res = artdata("card", split_dir, "--out", tmp_path / "card")
    assert res.exit_code == 0, res.output
    assert not (split_dir / CARD_NAME).exists()
    header = yaml.safe_load((tmp_path / "card" / CARD_NAME).read_text().split("---\n", 2)[1])
    assert header["configs"][0]["data_files"] == [{"split": "train", "path": ["../data/drawer/train/shard-00000.h5"]}]
    assert_loads_as_our_reader(offline, tmp_path / "card", "drawer", split_dir, tmp_path / "cache")


def test_croissant_validates_with_the_schema_and_checksums(data_root, tmp_path):
    import mlcroissant as mlc

    root = card_copy(data_root, tmp_path / "data")
    assert artdata("card", root).exit_code == 0
    path = root / CROISSANT_NAME
    dataset = mlc.Dataset(jsonld=path)  # raises on an invalid document
    assert not dataset.metadata.ctx.issues.errors and not dataset.metadata.ctx.issues.warnings
    doc = json.loads(path.read_text())
    assert doc["conformsTo"] == "http://mlcommons.org/croissant/1.1"
    for key in RAI_KEYS:
        assert doc.get(key), key
    assert len(RAI_SOURCES) == len(RAI_KEYS)
    assert "synthetic geometry" in json.dumps(doc["rai:personalSensitiveInformation"])
    # every file listed with its sha256 (a shard's is its manifest's: equal to the file's)
    files = {d["contentUrl"]: d for d in doc["distribution"] if d["@type"] == "cr:FileObject"}
    assert set(files) == {f"{c}/{s}/{n}" for c, s, *_ in SPLITS for n in ("manifest.json", "shard-00000.h5")}
    for url, d in files.items():
        assert d["sha256"] == hashlib.sha256((root / url).read_bytes()).hexdigest(), url
    # one record set per split; its fields are the schema's, with units and frames, read from the shards
    sets = {r["@id"]: r for r in doc["recordSet"]}
    assert set(sets) == {f"{c}/{s}" for c, s, *_ in SPLITS}
    fields = {f["name"]: f for f in sets["cabinet2/train"]["field"]}
    assert list(fields) == [f.name for f in FIELDS]
    for f in FIELDS:
        text = fields[f.name]["description"]
        assert f.description in text and f"Units: {f.units}" in text and f"frame: {f.frame}" in text
        assert fields[f.name]["source"] == {"fileSet": {"@id": "cabinet2/train/shards"}, "extract": {"column": f.name}}
    assert fields["depth"]["cr:arrayShape"] == "108,192" and fields["depth"]["dataType"] == "cr:Float32"
    assert fields["axis_pose"]["cr:arrayShape"] == "2,7" and fields["class"]["dataType"] == "sc:Text"
    colour = {f["name"]: f for f in sets["microwave/train"]["field"]}
    assert colour["rgb"]["cr:arrayShape"] == "108,192,3" and colour["rgb"]["dataType"] == "cr:UInt8"
    assert "visible_fraction" in colour and "visible_fraction" not in fields
    for set_id in sets:  # the declared shapes are the stored ones
        with Split(root / set_id) as split:
            for f in sets[set_id]["field"]:
                stored = split.shards[0].read(f["name"]).shape[1:]
                assert f.get("cr:arrayShape", "") == ",".join(str(d) for d in stored), (set_id, f["name"])


def test_existing_card_is_kept_unless_overwrite(data_root, tmp_path):
    root = card_copy(data_root, tmp_path / "data") / "drawer"
    (root / CARD_NAME).write_text("my own card\n")
    assert_one_line_error(artdata("card", root), "README.md exists", "--overwrite")
    assert (root / CARD_NAME).read_text() == "my own card\n" and not (root / CROISSANT_NAME).exists()
    res = artdata("card", root, "--overwrite")
    assert res.exit_code == 0, res.output
    assert (root / CARD_NAME).read_text().startswith("---\n")


def test_splits_a_card_cannot_publish_are_one_line(data_root, tmp_path):
    root = card_copy(data_root, tmp_path / "data")
    bad = root / "drawer" / "val-1"  # datasets accepts word characters and dots only
    shutil.copytree(root / "drawer" / "test", bad)
    assert_one_line_error(artdata("card", root), "val-1", "rename the folder")
    shutil.rmtree(bad)
    manifest = root / "drawer" / "test" / "manifest.json"
    m = json.loads(manifest.read_text())
    manifest.write_text(json.dumps({**m, "complete": False}))
    assert_one_line_error(artdata("card", root), "incomplete split")
    assert_one_line_error(artdata("card", root / "cabinet2", "--url", "huggingface.co/x"), "--url", "http")
    assert not (root / CARD_NAME).exists() and not (root / "cabinet2" / CARD_NAME).exists()


def test_missing_publish_extra_is_one_line(data_root, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "mlcroissant", None)  # as if not installed
    assert_one_line_error(artdata("card", card_copy(data_root, tmp_path / "data")), "mlcroissant", "pip install")


def test_real_captures_need_their_own_datasheet(data_root, tmp_path, offline):
    """The repository's datasheet describes synthetic data: ingested captures are published with
    the publisher's, which must hold the sections the RAI properties come from."""
    with Split(data_root / "drawer" / "test") as split:
        sh = split.shards[0]
        for k, name in enumerate(("a", "b")):
            s = sh.sample(k)
            write_capture(tmp_path / "caps", name, s, sh.K, {"q": s["q"].tolist(), "axis_pose": s["axis_pose"].tolist()})
    res = artdata("ingest", tmp_path / "caps", "--class", "drawer", "--out", tmp_path / "real", "-q")
    assert res.exit_code == 0, res.output
    split_dir = tmp_path / "real" / "drawer" / "real"
    assert_one_line_error(artdata("card", split_dir), "real captures", "--datasheet")
    sheet = tmp_path / "sheet.md"
    sheet.write_text("---\nlicense: cc-by-4.0\n---\n# Datasheet: our kitchen\n\n## Motivation\n\n"
                     "**Why was it created?**  To test estimators on our kitchen.\n")
    assert_one_line_error(artdata("card", split_dir, "--datasheet", sheet), "Collection process", "Known limitations")
    sections = {"Collection process": "Captured with a Kinect v2 in one kitchen, 2026.",
                "Composition": "**Missing information.**  Geometry and pose are not labelled.\n\n"
                               "**Labels.**  q measured with a tape.\n\n"
                               "**Confidential, offensive or personal data.**  No people in view.",
                "Preprocessing, cleaning, labelling": "Depth in mm, converted to metres.",
                "Uses": "**Intended.**  Evaluation.\n\n**Other possible uses.**  None.\n\n"
                        "**Not recommended.**  Training.\n\n**Composition risks to be aware of.**  One kitchen.",
                "Known limitations": "* **Two images.**  Far too few.",
                "Maintenance": "None."}
    sheet.write_text(sheet.read_text() + "".join(f"\n## {h}\n\n{t}\n" for h, t in sections.items()))
    res = artdata("card", split_dir, "--datasheet", sheet)
    assert res.exit_code == 0, res.output
    doc = json.loads((split_dir / CROISSANT_NAME).read_text())
    assert doc["rai:personalSensitiveInformation"] == "Confidential, offensive or personal data. No people in view."
    assert doc["license"] == "cc-by-4.0" and doc["rai:dataLimitations"] == "Two images. Far too few."
    assert "our kitchen" in (split_dir / CARD_NAME).read_text()
    assert_loads_as_our_reader(offline, split_dir, "drawer", split_dir, tmp_path / "cache")  # NaN labels too


def test_docs_name_every_datasheet_source():
    """docs/publishing.md tells a publisher of real captures which sections their datasheet needs."""
    from articulated_dataset.format.card import BULLETS, PURPOSE_SOURCE

    text = (ROOT / "docs" / "publishing.md").read_text()
    for heading, label in [src for sources in RAI_SOURCES.values() for src in sources] + [PURPOSE_SOURCE]:
        assert f"## {heading}" in text and (label in (None, BULLETS) or f"**{label}**" in text), (heading, label)
