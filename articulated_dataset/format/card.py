"""Publishing metadata for split folders: a Hugging Face dataset card and Croissant metadata.

:func:`write_card` describes the splits at a path (one split folder, a class folder or a data
root ``<class>/<split>/``) in two files written beside them (or into another folder):

* ``README.md``, a Hugging Face dataset card: a YAML header holding the datasheet's metadata
  (licence, task categories, tags), the size category, one ``configs`` entry per class with
  ``data_files`` per split, and ``dataset_info`` with the features of every stored field, so
  that ``datasets.load_dataset`` reads the HDF5 shards with its packaged ``hdf5`` builder (the
  features name the per-image datasets only; the file-level ``K`` and ``R_camera_to_optical``,
  3x3 each, are not records); then the splits' counts and settings, the field table (the
  schema's text), the datasheet and the citation;
* ``croissant.json``, Croissant 1.1 JSON-LD: every shard and manifest as a FileObject with its
  sha256, one FileSet and one RecordSet per split (the schema's fields, units and frames in
  their descriptions), and the Responsible-AI properties taken from the datasheet's sections
  (:data:`RAI_SOURCES`).

Everything the files say about a field comes from :mod:`.schema`; about the data, from the
manifests and shards (read through :class:`~articulated_dataset.format.Split`); about the
dataset's purpose, collection and limits, from the datasheet (the repository's
``DATASHEET.md`` unless another is given); the citation from ``CITATION.cff``.  The shards'
sha256 are the manifests' (``artdata verify`` checks them against the files).  ``datasets`` and
``mlcroissant`` are optional (the ``publish`` extra) and imported only here, when a card is
written.
"""

from __future__ import annotations

import datetime
import json
import logging
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import yaml

from articulated_dataset import __version__
from articulated_dataset.core.errors import DataFormatError, UserError, import_optional, option
from articulated_dataset.core.safeio import atomic_write_text, ensure_dir
from articulated_dataset.format.discovery import find_split_dirs
from articulated_dataset.format.manifest import MANIFEST_NAME, printable
from articulated_dataset.format.schema import FIELDS, OPTIONAL_FIELDS, RGB_FIELDS, Field, resolve_shape
from articulated_dataset.format.shards import json_list, sha256_file
from articulated_dataset.format.split import Split

log = logging.getLogger(__name__)

#: The dataset card's file name (what the Hugging Face Hub and ``datasets`` read).
CARD_NAME = "README.md"
#: The Croissant metadata's file name.
CROISSANT_NAME = "croissant.json"
#: The repository checkout holding the default datasheet and citation.
REPOSITORY_ROOT = Path(__file__).resolve().parents[2]
DATASHEET_NAME = "DATASHEET.md"
CITATION_NAME = "CITATION.cff"
#: How to install what writing a card needs.
PUBLISH_INSTALL = 'pip install "datasets>=4" "mlcroissant>=1.0" (or pip install -e ".[publish]" from the repository checkout)'
#: Croissant version the metadata conforms to (``isArray``/``arrayShape`` fields are 1.1's).
CROISSANT_VERSION = "http://mlcommons.org/croissant/1.1"
#: Media types of the files a card lists.
HDF5_MEDIA_TYPE = "application/x-hdf5"
JSON_MEDIA_TYPE = "application/json"
#: Split names ``datasets`` accepts (its ``naming._split_re``): word characters, dot-separated.
HF_SPLIT_NAME = re.compile(r"\w+(\.\w+)*")
#: The Hugging Face Hub's ``size_categories`` values: (upper bound of images, category).
SIZE_CATEGORIES = ((1_000, "n<1K"), (10_000, "1K<n<10K"), (100_000, "10K<n<100K"), (1_000_000, "100K<n<1M"),
                   (10_000_000, "1M<n<10M"), (100_000_000, "10M<n<100M"), (1_000_000_000, "100M<n<1B"))
#: Largest datasheet or citation file read (the repository's datasheet is about 25 kB).
MAX_TEXT_BYTES = 1 << 20
#: Marker in :data:`RAI_SOURCES`: one text per bullet of the section.
BULLETS = "bullets"
#: Croissant Responsible-AI properties (``mlcroissant.Metadata`` arguments) and the datasheet text
#: each is taken from: (section heading, bold paragraph label), (heading, None) for the whole
#: section, or (heading, :data:`BULLETS`) for each of its bullets.  A datasheet given with
#: ``--datasheet`` needs them all (docs/publishing.md lists them).
RAI_SOURCES: dict[str, list[tuple[str, str | None]]] = {
    "data_collection": [("Collection process", None)],
    "data_collection_missing_data": [("Composition", "Missing information.")],
    "data_preprocessing_protocol": [("Preprocessing, cleaning, labelling", None)],
    "data_annotation_protocol": [("Composition", "Labels.")],
    "data_use_cases": [("Uses", "Intended."), ("Uses", "Other possible uses."), ("Uses", "Not recommended.")],
    "data_biases": [("Uses", "Composition risks to be aware of."), ("Known limitations", BULLETS)],
    "data_limitations": [("Known limitations", BULLETS)],
    "personal_sensitive_information": [("Composition", "Confidential, offensive or personal data.")],
    "data_release_maintenance_plan": [("Maintenance", None)],
}
#: RAI properties that hold one text (the others a list of texts).
RAI_SINGLE_TEXT = ("data_collection", "data_collection_missing_data", "data_release_maintenance_plan")
#: The datasheet paragraph that opens the Croissant description.
PURPOSE_SOURCE = ("Motivation", "Why was it created?")
#: A Markdown link to a relative target (a file of the repository): on the Hub it leads nowhere,
#: so the card keeps its text only.
RELATIVE_LINK = re.compile(r"\[([^\]]+)\]\((?![a-z][a-z0-9+.-]*:|#)[^)]*\)")


@dataclass(frozen=True)
class CardSplit:
    """What a card says of one split folder (read through :class:`Split`)."""

    path: Path
    class_name: str
    name: str
    n_objects: int
    n_images: int
    shard_paths: tuple[Path, ...]
    records: tuple[dict, ...]  # the manifest's shard records (file, n_images, bytes, sha256)
    fields: tuple[Field, ...]  # stored per-image fields, schema order
    shapes: dict  # field name -> shape of one image's value
    intrinsics: tuple | None  # (fx, fy, cx, cy) px when every shard has the same K, else None
    joints: tuple[str, ...]  # "name (type)" per joint, label order
    format_version: str
    package_version: str
    real: bool
    settings: str

    @property
    def signature(self) -> tuple:
        """What must agree between the splits of one ``datasets`` config: the features."""
        return tuple((f.name, self.shapes[f.name]) for f in self.fields)


def _settings(split: Split) -> str:
    """The split's settings beyond the paper's defaults, as words."""
    if split.is_real:
        return "ingested real captures"
    config = split.config_dict
    parts = [f"seed {config.get('seed')}"]
    camera = config.get("camera", {}) if isinstance(config.get("camera"), dict) else {}
    for key in ("mount", "intrinsics"):
        if key in camera:
            parts.append(f"camera {key} {camera[key]}")
    for key in ("noise", "scene", "occluders", "framing"):
        if key in config and config[key] not in ("none", 0):
            parts.append(f"{key} {config[key]}")
    if config.get("rgb"):
        parts.append("rgb")
    if config.get("mean"):
        parts.append("the class's mean object")
    if config.get("third_party"):
        parts.append("third-party URDF")
    return printable(", ".join(str(p) for p in parts))


def describe_split(split_dir: Path) -> CardSplit:
    """A :class:`CardSplit` of ``split_dir``; a split a card cannot publish (incomplete, empty,
    shards that disagree, a split name ``datasets`` refuses) is a :class:`UserError`."""
    with Split(split_dir) as split:
        if not split.complete:
            raise UserError(f"{split_dir}: incomplete split; finish it ('artdata generate ... {option('resume')}') "
                            "before publishing it")
        if not split.shards:
            raise UserError(f"{split_dir}: the manifest lists no shards; nothing to publish")
        if not HF_SPLIT_NAME.fullmatch(split.name):
            raise UserError(f"{split_dir}: split name {printable(split.name)[:80]!r} is not one the Hugging Face "
                            "datasets library accepts (letters, digits and underscores, dot-separated); rename the folder")
        signatures, Ks = set(), set()
        for shard, record in zip(split.shards, split.manifest["shards"]):
            f = shard.file
            _, height, width = f["depth"].shape
            joints = int(shard.attrs["n_joints"])
            fields = tuple(fl for fl in FIELDS + OPTIONAL_FIELDS + RGB_FIELDS if fl.name in f)
            signatures.add((fields, height, width, joints))
            Ks.add(tuple(float(x) for x in shard.K[[0, 1, 0, 1], [0, 1, 2, 2]]))
            if not isinstance(record.get("sha256"), str) or not isinstance(record.get("bytes"), int):
                raise DataFormatError(f"{split_dir / MANIFEST_NAME}: no sha256 or size for {record['file']} "
                                      "(run 'artdata verify')")
            size = shard.path.stat().st_size
            if size != record["bytes"]:
                raise DataFormatError(f"{shard.path}: {size} bytes, the manifest says {record['bytes']} "
                                      "(run 'artdata verify')")
        if len(signatures) != 1:
            raise DataFormatError(f"{split_dir}: its shards store different fields or image sizes (run 'artdata verify')")
        (fields, height, width, joints), = signatures
        names, types = split.joint_names(), json_list(split.attrs.get("joint_types", "[]")) or []
        return CardSplit(
            path=Path(split_dir), class_name=split.class_name, name=split.name,
            n_objects=int(split.manifest.get("n_objects", 0)), n_images=sum(len(sh) for sh in split.shards),
            shard_paths=tuple(split.shard_paths), records=tuple(split.manifest["shards"]), fields=fields,
            shapes={fl.name: resolve_shape(fl.shape, N=1, J=joints, H=height, W=width)[1:] for fl in fields},
            intrinsics=next(iter(Ks)) if len(Ks) == 1 else None,
            joints=tuple(printable(f"{n} ({t})") for n, t in zip(names, types)),
            format_version=str(split.manifest.get("format_version", "")),
            package_version=str(split.manifest.get("package_version", "")),
            real=split.is_real, settings=_settings(split))


def group_configs(splits: list[CardSplit]) -> dict[str, list[CardSplit]]:
    """``{config name: splits}``: one ``datasets`` config per class, or one per split of a class
    whose splits store different features (``<class>-<split>``: e.g. another image size)."""
    by_class: dict[str, list[CardSplit]] = {}
    for s in splits:
        by_class.setdefault(s.class_name, []).append(s)
    configs: dict[str, list[CardSplit]] = {}
    for class_name, group in sorted(by_class.items()):
        named = {class_name: group} if len({s.signature for s in group}) == 1 else {
            f"{class_name}-{s.name}": [s] for s in group}
        for name, members in named.items():
            split_names = [s.name for s in members]
            twice = sorted({n for n in split_names if split_names.count(n) > 1})
            if name in configs or twice:
                raise UserError(f"two splits would both be published as config {name!r}, split "
                                f"{(twice or split_names)[0]!r} ({', '.join(str(s.path) for s in members[:3])}); "
                                "give them separately")
            configs[name] = members
    return configs


# --------------------------------------------------------------------------------------
# the datasheet and the citation

def read_text(path: Path, what: str) -> str:
    """The UTF-8 text of a small regular file (a datasheet, a citation); anything else is a
    one-line :class:`UserError` (a FIFO or device would block or never end)."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise UserError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise UserError(f"{what} {path} is not a regular file")
    if st.st_size > MAX_TEXT_BYTES:
        raise UserError(f"{what} {path} is {st.st_size} bytes; at most {MAX_TEXT_BYTES} are read")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read {what} {path}: {exc}") from None


def front_matter(text: str, path: Path, what: str) -> tuple[dict, str]:
    """``(YAML header as a dict, the rest)`` of a Markdown file that starts with ``---``."""
    if not text.startswith("---\n") or "\n---\n" not in text[3:]:
        return {}, text
    header, body = text[4:].split("\n---\n", 1)
    try:
        meta = yaml.safe_load(header)
    except (yaml.YAMLError, RecursionError) as exc:  # RecursionError: '[[[[...' nested past the parser's limit
        raise UserError(f"{what} {path}: unreadable YAML header ({' '.join(str(exc).split())[:200]})") from None
    if not isinstance(meta, dict):
        raise UserError(f"{what} {path}: its YAML header is not a mapping")
    return meta, body


@dataclass(frozen=True)
class Datasheet:
    """A datasheet in Markdown: its YAML header (dataset-card metadata) and its ``## `` sections."""

    path: Path
    meta: dict
    body: str

    @classmethod
    def read(cls, path: Path) -> "Datasheet":
        """The datasheet at ``path``; a header without a ``license`` string is the user's mistake."""
        meta, body = front_matter(read_text(path, "datasheet"), path, "datasheet")
        if not isinstance(meta.get("license"), str):
            raise UserError(f"datasheet {path}: its YAML header names no licence ('license: ...', e.g. mit)")
        return cls(path, meta, body)

    def sections(self) -> dict[str, str]:
        """``{heading: text}`` of the ``## `` sections (``#`` lines inside code blocks are code)."""
        out: dict[str, list[str]] = {}
        current, fenced = None, False
        for line in self.body.splitlines():
            if line.startswith("```"):
                fenced = not fenced
            if not fenced and line.startswith("## "):
                current = line[3:].strip()
                out[current] = []
            elif current is not None:
                out[current].append(line)
        return {k: "\n".join(v).strip() for k, v in out.items()}

    def text(self, heading: str, label: str | None) -> list[str]:
        """The texts :data:`RAI_SOURCES` names: a whole section, each bullet of it, or its
        paragraph opening with ``**label**`` (links to repository files kept as text); empty
        if the datasheet lacks it."""
        section = self.sections().get(heading)
        if section is None:
            return []
        if label is None:
            return [RELATIVE_LINK.sub(r"\1", section)]
        if label == BULLETS:
            items: list[list[str]] = []
            for line in section.splitlines():
                if line.startswith(("* ", "- ")):
                    items.append([line[2:]])
                elif items and line.startswith(" ") and line.strip():
                    items[-1].append(line.strip())
            return [_one_paragraph(" ".join(item)) for item in items]
        for paragraph in re.split(r"\n\s*\n", section):
            if paragraph.startswith(f"**{label}**"):
                return [_one_paragraph(paragraph)]
        return []

    def missing(self) -> list[str]:
        """The sections and paragraphs of :data:`RAI_SOURCES` (and the purpose) it lacks."""
        wanted = [src for sources in RAI_SOURCES.values() for src in sources] + [PURPOSE_SOURCE]
        sections, out = self.sections(), []
        for heading, label in wanted:
            name = heading if heading not in sections or label in (None, BULLETS) else f"{heading}: {label}"
            if not self.text(heading, label) and name not in out:
                out.append(name)
        return out


def _one_paragraph(text: str) -> str:
    return RELATIVE_LINK.sub(r"\1", " ".join(text.replace("**", "").split()))


def card_body_of(sheet: Datasheet) -> str:
    """The datasheet's text for the card: its title dropped and its headings one level down
    (under the card's "Datasheet"), links to repository files kept as text."""
    lines, fenced = [], False
    body = sheet.body.strip().splitlines()
    if body and body[0].startswith("# "):
        body = "\n".join(body[1:]).strip().splitlines()
    for line in body:
        if line.startswith("```"):
            fenced = not fenced
        lines.append("#" + line if not fenced and line.startswith("#") else RELATIVE_LINK.sub(r"\1", line))
    return "\n".join(lines)


def read_citation(path: Path) -> dict:
    """The CITATION.cff at ``path`` as a dict; unreadable YAML or a file without a title is the user's mistake."""
    try:
        cff = yaml.safe_load(read_text(path, "citation file"))
    except (yaml.YAMLError, RecursionError) as exc:
        raise UserError(f"citation file {path}: unreadable YAML ({' '.join(str(exc).split())[:200]})") from None
    if not isinstance(cff, dict) or not isinstance(cff.get("title"), str):
        raise UserError(f"citation file {path}: not a CITATION.cff (no title)")
    return cff


def _bibtex_authors(authors) -> str:
    names = []
    for a in authors if isinstance(authors, list) else []:
        if isinstance(a, dict) and a.get("family-names"):
            names.append(f"{a['family-names']}, {a.get('given-names', '')}".strip(", "))
        elif isinstance(a, dict) and a.get("name"):
            names.append("{" + str(a["name"]) + "}")
    return " and ".join(names)


def _bibtex_entry(kind: str, key: str, fields: dict) -> str:
    body = ",\n".join(f"  {k} = {{{v}}}" for k, v in fields.items() if v not in (None, ""))
    return f"@{kind}{{{key},\n{body}\n}}"


def bibtex(cff: dict) -> str:
    """BibTeX of a CITATION.cff: its preferred citation (the paper), then the software itself."""
    entries = []
    paper = cff.get("preferred-citation")
    if isinstance(paper, dict) and paper.get("title"):
        authors = paper.get("authors") or []
        first = authors[0].get("family-names", "") if authors and isinstance(authors[0], dict) else ""
        key = re.sub(r"\W", "", f"{first}{paper.get('year', '')}".lower()) or "paper"
        conference = paper.get("type") == "conference-paper"
        venue = paper.get("collection-title") or (paper.get("conference") or {}).get("name")
        entries.append(_bibtex_entry("inproceedings" if conference else "misc", key, {
            "title": paper["title"], "author": _bibtex_authors(authors),
            "booktitle" if conference else "howpublished": venue, "year": paper.get("year")}))
    released = str(cff.get("date-released", ""))
    entries.append(_bibtex_entry("software", re.sub(r"\W", "", cff["title"].split(":")[0]) or "software", {
        "title": cff["title"], "author": _bibtex_authors(cff.get("authors")), "version": cff.get("version"),
        "year": released[:4], "license": cff.get("license"), "url": cff.get("repository-code") or cff.get("url")}))
    return "\n\n".join(entries)


# --------------------------------------------------------------------------------------
# the two files

def field_text(field: Field) -> str:
    """A field's description with its units, frame and dtype (the schema's words)."""
    return f"{field.description} Units: {field.units}; frame: {field.frame}; stored as {field.dtype}."


def size_category(n_images: int) -> str:
    """The Hugging Face Hub's ``size_categories`` value for ``n_images`` images."""
    for bound, category in SIZE_CATEGORIES:
        if n_images < bound:
            return category
    return "n>1B"


def relative(path: Path, out: Path) -> str:
    """``path`` relative to the card's folder, with forward slashes (the card's data paths)."""
    return Path(os.path.relpath(path.resolve(), out.resolve())).as_posix()


def hf_features(datasets, split: CardSplit):
    """The ``datasets.Features`` of a split's records: one per stored per-image field."""
    features = {}
    for f in split.fields:
        shape = split.shapes[f.name]
        if f.dtype.startswith("S"):  # fixed-length ASCII bytes: read as text
            features[f.name] = datasets.Value("string")
        elif not shape:
            features[f.name] = datasets.Value(f.dtype)
        elif len(shape) == 1:
            features[f.name] = datasets.List(datasets.Value(f.dtype), length=shape[0])
        else:
            features[f.name] = getattr(datasets, f"Array{len(shape)}D")(shape=shape, dtype=f.dtype)
    return datasets.Features(features)


def card_header(configs: dict[str, list[CardSplit]], sheet: Datasheet, out: Path) -> dict:
    """The card's YAML header: the datasheet's metadata, the size category, and the
    ``dataset_info`` and ``configs`` that ``datasets`` reads (written by its own writers)."""
    datasets = import_optional("datasets", "artdata card", PUBLISH_INSTALL)
    info_mod = import_optional("datasets.info", "artdata card", PUBLISH_INSTALL)
    metadata_mod = import_optional("datasets.utils.metadata", "artdata card", PUBLISH_INSTALL)
    header = {k: v for k, v in sheet.meta.items() if k not in ("configs", "dataset_info", "size_categories")}
    header["size_categories"] = [size_category(sum(s.n_images for group in configs.values() for s in group))]
    infos: dict = {}
    metadata: dict[str, dict] = {}
    for k, (name, group) in enumerate(configs.items()):
        splits = datasets.SplitDict()
        for s in group:
            splits.add(datasets.SplitInfo(name=s.name, num_examples=s.n_images))
        infos[name] = datasets.DatasetInfo(features=hf_features(datasets, group[0]), splits=splits)
        metadata[name] = {"data_files": [{"split": s.name, "path": [relative(p, out) for p in s.shard_paths]}
                                         for s in group]}
        if k == 0 and len(configs) > 1:  # load_dataset(folder) without a config name reads the first class
            metadata[name]["default"] = True
    info_mod.DatasetInfosDict(infos).to_dataset_card_data(header)
    metadata_mod.MetadataConfigs(metadata).to_dataset_card_data(header)
    return header


def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def card_markdown(configs: dict[str, list[CardSplit]], sheet: Datasheet, cff: dict, out: Path) -> str:
    """The whole ``README.md``."""
    header = card_header(configs, sheet, out)
    splits = [s for group in configs.values() for s in group]
    title = sheet.meta.get("pretty_name") or "Articulated-object depth images"
    first_config, first = next(iter(configs.items()))
    rows = ["| config | split | objects | images | shards | image size (px) | fx, fy, cx, cy (px) | joints | format | "
            "settings |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name, group in configs.items():
        for s in group:
            height, width = s.shapes["depth"]
            k = ", ".join(f"{x:.6g}" for x in s.intrinsics) if s.intrinsics else "per shard (dataset K)"
            rows.append("| " + " | ".join(_cell(c) for c in (
                name, s.name, s.n_objects, s.n_images, len(s.shard_paths), f"{width} x {height}", k,
                "; ".join(s.joints), s.format_version, s.settings)) + " |")
    fields = {f.name: f for s in splits for f in s.fields}
    field_rows = ["| field | dtype | shape per image | units | frame | meaning |", "|---|---|---|---|---|---|"]
    for f in FIELDS + OPTIONAL_FIELDS + RGB_FIELDS:
        if f.name in fields:
            shape = "(" + ", ".join(str(d) for d in f.shape[1:]) + ")" if len(f.shape) > 1 else "scalar"
            field_rows.append("| " + " | ".join(_cell(c) for c in (f"`{f.name}`", f.dtype, shape, f.units, f.frame,
                                                                       f.description)) + " |")
    images = sum(s.n_images for s in splits)
    objects = sum(s.n_objects for s in splits)
    source = ("ingested real captures" if all(s.real for s in splits) else
              "synthetic depth images rendered by articulated_dataset" if not any(s.real for s in splits) else
              "synthetic depth images and ingested real captures")
    parts = [
        "---", yaml.safe_dump(header, sort_keys=False, allow_unicode=True).rstrip(), "---", "",
        f"# {title}", "",
        f"{images:,} labelled {source} ({objects:,} objects, {len(splits)} split(s) of {len(configs)} config(s)), "
        "stored as HDF5 shards with one JSON manifest per split (shard format specification: docs/format.md of "
        "the articulated_dataset repository).  This card and croissant.json were written by `artdata card` "
        f"(articulated_dataset {__version__}) from the manifests, the shards and the package's schema.", "",
        "## Contents", "", *rows, "",
        "Symbols in shapes: J joints, H x W pixels, P = 1 + J (body and moving parts).", "",
        "## Loading", "",
        "With `datasets` 4 or later (its packaged HDF5 builder reads the shards; the `dataset_info` features "
        "above select the per-image datasets):", "",
        "```python",
        "from datasets import load_dataset",
        "",
        f'ds = load_dataset("USER/NAME", "{first_config}", split="{first[0].name}")  # or the folder holding this card',
        'sample = ds.with_format("numpy")[0]  # sample["depth"]: (H, W) float32 metres',
        "```", "",
        "The camera's intrinsics `K` and the rotation `R_camera_to_optical` (3 x 3 each) are file-level datasets of "
        "every shard, not records: read them with `h5py.File(shard)[\"K\"][()]`, or open a downloaded split folder "
        "with `articulated_dataset` (`articulated_dataset.format.Split`, the PyTorch and JAX loaders), which checks "
        "every shard.", "",
        "## Fields", "", *field_rows, "",
        "## Croissant", "",
        f"`{CROISSANT_NAME}` describes the same files in Croissant 1.1 (every shard with its sha256, one record set "
        "per split, the fields above with units and frames, and the Responsible-AI properties taken from the "
        "datasheet below).  `mlcroissant` validates it; it reads no HDF5, so its records are read with `datasets` "
        "or h5py.", "",
        "## Datasheet", "",
        "The datasheet of the data's generator follows; it describes the paper-size dataset, and the counts of "
        "this upload are those of Contents above.", "",
        card_body_of(sheet), "",
        "## Citation", "", "```bibtex", bibtex(cff), "```", "",
    ]
    return "\n".join(parts)


def croissant_json(configs: dict[str, list[CardSplit]], sheet: Datasheet, cff: dict, out: Path,
                   url: str | None = None) -> dict:
    """The Croissant JSON-LD, built and checked by ``mlcroissant`` (an issue is a bug here)."""
    mlc = import_optional("mlcroissant", "artdata card", PUBLISH_INSTALL)
    ctx = mlc.Context(conforms_to=CROISSANT_VERSION)
    distribution, record_sets = [], []
    for config, group in configs.items():
        for s in group:
            set_id = f"{config}/{s.name}"
            manifest = s.path / MANIFEST_NAME
            distribution.append(mlc.FileObject(
                ctx=ctx, id=relative(manifest, out), name=relative(manifest, out), content_url=relative(manifest, out),
                encoding_formats=[JSON_MEDIA_TYPE], sha256=sha256_file(manifest),
                content_size=f"{manifest.stat().st_size} B",
                description=f"manifest of split {s.name} of {s.class_name}: shard list, checksums, generation config"))
            for path, record in zip(s.shard_paths, s.records):
                distribution.append(mlc.FileObject(
                    ctx=ctx, id=relative(path, out), name=relative(path, out), content_url=relative(path, out),
                    encoding_formats=[HDF5_MEDIA_TYPE], sha256=record["sha256"], content_size=f"{record['bytes']} B",
                    description=f"{record['n_images']} images of split {s.name} of {s.class_name}"))
            distribution.append(mlc.FileSet(
                ctx=ctx, id=f"{set_id}/shards", name=f"{set_id}/shards", encoding_formats=[HDF5_MEDIA_TYPE],
                includes=[relative(s.path, out) + "/shard-*.h5" if relative(s.path, out) != "." else "shard-*.h5"],
                description=f"the HDF5 shards of split {s.name} of {s.class_name}"))
            fields = []
            for f in s.fields:
                shape = s.shapes[f.name]
                fields.append(mlc.Field(
                    ctx=ctx, id=f"{set_id}/{f.name}", name=f.name, description=field_text(f),
                    data_types=[mlc.DataType.TEXT if f.dtype.startswith("S") else getattr(mlc.DataType, f.dtype.upper())],
                    is_array=True if shape else None, array_shape=",".join(str(d) for d in shape) if shape else None,
                    source=mlc.Source(ctx=ctx, file_set=f"{set_id}/shards", extract=mlc.Extract(ctx=ctx, column=f.name))))
            record_sets.append(mlc.RecordSet(
                ctx=ctx, id=set_id, name=set_id, fields=fields,
                description=(f"one record per image of split {s.name} of {s.class_name} ({s.n_images} images): each "
                             "field is the HDF5 dataset of that name in the shards, indexed by image")))
    rai = {}
    for prop, sources in RAI_SOURCES.items():
        texts = [t for heading, label in sources for t in sheet.text(heading, label)]
        rai[prop] = "\n\n".join(texts) if prop in RAI_SINGLE_TEXT else texts
    splits = [s for group in configs.values() for s in group]
    versions = {s.package_version for s in splits}
    license_id, spdx = str(sheet.meta["license"]), str(cff.get("license", ""))
    metadata = mlc.Metadata(
        ctx=ctx, name=str(sheet.meta.get("pretty_name") or "articulated-object depth images"),
        description=(" ".join(sheet.text(*PURPOSE_SOURCE)) + f" This copy: {sum(s.n_images for s in splits)} images "
                     f"of {len(splits)} split(s) ({', '.join(configs)}); depth and mask per image with exact labels; "
                     "the camera intrinsics K are a file-level dataset of each shard."),
        cite_as=bibtex(cff), url=url, date_published=datetime.datetime.now(datetime.timezone.utc).date(),
        version=versions.pop() if len(versions) == 1 else __version__,
        license=[f"https://spdx.org/licenses/{spdx}.html" if spdx.lower() == license_id.lower() else license_id],
        keywords=[str(t) for t in tags] if isinstance(tags := sheet.meta.get("tags"), list) and tags else None,
        creators=[mlc.Organization(ctx=ctx, name=str(a["name"])) if "name" in a else
                  mlc.Person(ctx=ctx, name=f"{a.get('given-names', '')} {a.get('family-names', '')}".strip())
                  for a in cff.get("authors", []) if isinstance(a, dict)],
        distribution=distribution, record_sets=record_sets, **rai)
    if ctx.issues.errors:
        raise RuntimeError(f"the Croissant metadata does not validate: {ctx.issues.report()}")
    for warning in ctx.issues.warnings:
        log.warning("croissant: %s", warning)
    return metadata.to_json()


def write_card(path: str | Path, out: str | Path | None = None, *, overwrite: bool = False,
               datasheet: str | Path | None = None, citation: str | Path | None = None,
               url: str | None = None) -> list[Path]:
    """Write ``README.md`` (Hugging Face dataset card) and ``croissant.json`` for the splits at
    ``path`` into ``out`` (default: ``path``); their data paths are relative to ``out``.  An
    existing card is refused unless ``overwrite``.  A datasheet other than the repository's must
    hold the sections :data:`RAI_SOURCES` names; ingested real captures need one (the repository's
    describes synthetic data).  Returns the two files' paths."""
    root = Path(path)
    out = Path(out) if out is not None else root
    if url is not None and not (urlsplit(url).scheme in ("http", "https") and urlsplit(url).netloc):
        raise UserError(f"{option('url')} {printable(url)[:120]!r} is not an http(s) address of the dataset's page")
    targets = [out / CARD_NAME, out / CROISSANT_NAME]
    from articulated_dataset.core.safeio import check_name_length

    for target in targets:  # a name too long for the filesystem is one line, before it is looked at
        check_name_length(target)
    if not overwrite:
        for target in targets:
            if target.exists() or target.is_symlink():
                raise UserError(f"{target} exists; pass {option('overwrite')} to replace it")
    import_optional("datasets", "artdata card", PUBLISH_INSTALL)  # both, before anything is read
    import_optional("mlcroissant", "artdata card", PUBLISH_INSTALL)
    splits = [describe_split(d) for d in find_split_dirs(root)]
    if datasheet is None and any(s.real for s in splits):
        raise UserError(f"{root} holds ingested real captures ({next(s.path for s in splits if s.real)}); the "
                        f"repository's datasheet describes synthetic data: pass {option('datasheet')} FILE describing "
                        "how they were collected (docs/publishing.md lists its sections)")
    if datasheet is None and not (REPOSITORY_ROOT / DATASHEET_NAME).is_file():
        raise UserError(f"no {DATASHEET_NAME} beside the package (an installed wheel ships none): pass "
                        f"{option('datasheet')} FILE and {option('citation')} FILE (the repository's {DATASHEET_NAME} "
                        f"and {CITATION_NAME})")
    sheet = Datasheet.read(Path(datasheet) if datasheet is not None else REPOSITORY_ROOT / DATASHEET_NAME)
    missing = sheet.missing()
    if missing:
        raise UserError(f"datasheet {sheet.path} lacks what the Croissant RAI properties are taken from: "
                        + "; ".join(missing) + " (docs/publishing.md lists the sections)")
    cff = read_citation(Path(citation) if citation is not None else REPOSITORY_ROOT / CITATION_NAME)
    configs = group_configs(splits)
    ensure_dir(out)
    readme = card_markdown(configs, sheet, cff, out)
    croissant = json.dumps(croissant_json(configs, sheet, cff, out, url), indent=1, ensure_ascii=False) + "\n"
    atomic_write_text(targets[0], readme)
    atomic_write_text(targets[1], croissant)
    return targets
