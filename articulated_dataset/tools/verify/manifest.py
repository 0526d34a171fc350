"""Manifest checks of ``artdata verify``: the manifest's keys, version and shard records, its
generation config, the counts of a generated split and the ``real`` record of an ingested one.
Each finding is a :class:`Problem` naming the file."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from articulated_dataset.core.errors import DataFormatError, UserError
from articulated_dataset.core.mujoco_support import different_mujoco
from articulated_dataset.format import MANIFEST_NAME, check_version, shard_name
from articulated_dataset.format.shards import JSON_TEXT_ERRORS
from articulated_dataset.tools.verify.shard import one_line

#: Manifest keys the generator writes and the checks below read.
MANIFEST_KEYS = ("format_version", "class_name", "split", "seed", "complete", "n_objects", "n_images",
                 "n_shards_expected", "config", "shards")
SHARD_RECORD_KEYS = ("file", "n_images", "bytes", "sha256", "object_start", "object_stop")


@dataclass(frozen=True)
class Problem:
    """One finding: ``where`` is a file name inside the split folder."""

    where: str
    message: str
    warning: bool = False

    def __str__(self) -> str:
        return f"{self.where}: {'warning: ' if self.warning else ''}{self.message}"


def load_manifest(split_dir: Path) -> tuple[dict | None, list[Problem]]:
    """``(manifest, [])`` for the split's readable, well-formed manifest, else ``(None, [the problem])``: missing,
    corrupt JSON, missing keys, an unreadable format version, a corrupt shard list or non-integer counts."""
    path = split_dir / MANIFEST_NAME
    if not path.is_file():
        return None, [Problem(MANIFEST_NAME, "missing (not a complete generated split; shards checked without it)")]
    try:
        manifest = json.loads(path.read_text())
    except JSON_TEXT_ERRORS as exc:
        return None, [Problem(MANIFEST_NAME, f"corrupt JSON ({one_line(exc)})")]
    except OSError as exc:
        return None, [Problem(MANIFEST_NAME, f"cannot read ({exc.strerror or exc})")]
    if not isinstance(manifest, dict):
        return None, [Problem(MANIFEST_NAME, "corrupt: top level is not a JSON object")]
    missing = [k for k in MANIFEST_KEYS if k not in manifest]
    if missing:
        return None, [Problem(MANIFEST_NAME, f"missing keys {missing}")]
    try:
        check_version(str(manifest["format_version"]))
    except DataFormatError as exc:
        return None, [Problem(MANIFEST_NAME, str(exc))]
    if not isinstance(manifest["shards"], list) or not all(_valid_record(r) for r in manifest["shards"]):
        return None, [Problem(MANIFEST_NAME, f"corrupt shard list (each entry needs {list(SHARD_RECORD_KEYS)}: "
                                             f"a plain file name, integer counts and a hex sha256)")]
    bad = [k for k in ("n_images", "n_objects", "n_shards_expected", "seed") if not _is_int(manifest[k])]
    if bad or not isinstance(manifest["config"], dict):
        return None, [Problem(MANIFEST_NAME, f"corrupt: {bad or 'config'} must be {'integers' if bad else 'an object'}")]
    return manifest, []


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _valid_record(r) -> bool:
    """A manifest shard record with the generator's keys and types."""
    return (isinstance(r, dict) and all(k in r for k in SHARD_RECORD_KEYS)
            and isinstance(r["file"], str) and r["file"] == Path(r["file"]).name and r["file"] not in ("", ".", "..")
            and isinstance(r["sha256"], str)
            and all(_is_int(r[k]) for k in ("n_images", "bytes", "object_start", "object_stop")))


def manifest_config(manifest: dict):
    """The manifest's :class:`~articulated_dataset.format.SplitConfig` (checked against the
    class's registry entry for a registered class), or a problem message."""
    from articulated_dataset.classes.registry import check_table, get_class
    from articulated_dataset.format import SplitConfig

    try:
        config = SplitConfig.from_dict(manifest["config"])
        if config.third_party is None:
            check_table(get_class(config.class_name), config.table)
        return config, None
    except UserError as exc:
        return None, f"invalid generation config ({exc})"
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        return None, f"corrupt generation config ({type(exc).__name__}: {one_line(exc)})"


def check_mujoco_version(manifest: dict) -> list[Problem]:
    """A note (a warning, not a failure) where the split was rendered with another MuJoCo release
    than the installed one: regenerating it here need not give the same bytes.  A recorded
    version that is no version string is a problem."""
    try:
        other = different_mujoco(manifest, MANIFEST_NAME)
    except DataFormatError as exc:
        return [Problem(MANIFEST_NAME, str(exc).split(": ", 1)[-1])]
    if other is None:
        return []
    return [Problem(MANIFEST_NAME, f"{other}: a split regenerated here may differ in its bytes "
                                   "(docs/generation.md, Reproducibility)", warning=True)]


def check_manifest_counts(manifest: dict, config) -> list[Problem]:
    """Problems of the manifest's counts: against its shard records (images, objects, duplicate files) and, given the
    split's ``config``, against the shards, objects and images the config implies and its completeness."""
    out = []
    records = manifest["shards"]
    files = [r["file"] for r in records]
    if len(set(files)) != len(files):
        out.append(Problem(MANIFEST_NAME, "shard list names a file twice"))
    n_images = sum(int(r["n_images"]) for r in records)
    n_objects = sum(int(r["object_stop"]) - int(r["object_start"]) for r in records)
    if manifest["n_images"] != n_images:
        out.append(Problem(MANIFEST_NAME, f"n_images is {manifest['n_images']} but the shards hold {n_images}"))
    if manifest["n_objects"] != n_objects:
        out.append(Problem(MANIFEST_NAME, f"n_objects is {manifest['n_objects']} but the shards hold {n_objects}"))
    for key in ("class_name", "split", "seed"):
        if config is not None and manifest[key] != getattr(config, key):
            out.append(Problem(MANIFEST_NAME, f"{key} {manifest[key]!r} differs from its config's {getattr(config, key)!r}"))
    if config is None:
        return out
    if manifest["n_shards_expected"] != config.n_shards:
        out.append(Problem(MANIFEST_NAME, f"n_shards_expected is {manifest['n_shards_expected']}, config gives {config.n_shards}"))
    for r in records:
        try:
            index = int(Path(r["file"]).stem.split("-")[1])
        except (IndexError, ValueError):
            out.append(Problem(MANIFEST_NAME, f"unexpected shard file name {r['file']!r}"))
            continue
        objects = config.shard_objects(index)
        if r["file"] != shard_name(index) or (r["object_start"], r["object_stop"]) != (objects.start, objects.stop):
            out.append(Problem(MANIFEST_NAME, f"{r['file']}: objects [{r['object_start']}, {r['object_stop']}) "
                                              f"do not match the config's [{objects.start}, {objects.stop})"))
        elif r["n_images"] != len(objects) * config.images_per_object:
            out.append(Problem(MANIFEST_NAME, f"{r['file']}: {r['n_images']} images, config gives "
                                              f"{len(objects) * config.images_per_object}"))
    complete = len(records) == config.n_shards and n_objects == config.n_objects
    if not complete:
        out.append(Problem(MANIFEST_NAME, f"incomplete split: {len(records)} of {config.n_shards} shards "
                                          f"({n_objects} of {config.n_objects} objects); finish it with the same "
                                          f"'artdata generate' command plus --resume"))
    elif manifest["complete"] is not True:
        out.append(Problem(MANIFEST_NAME, "every shard is present but 'complete' is not true"))
    return out


def check_real_manifest(manifest: dict, config) -> tuple[list[Problem], dict]:
    """Counts of an ingested real split from its ``real`` record (objects, captures), and the
    captures each shard should hold (``{file: [names]}``; empty when the record is unusable)."""
    out = []
    rec = manifest["real"]
    if not isinstance(rec, dict):
        return [Problem(MANIFEST_NAME, "corrupt: 'real' must be an object with 'objects' and 'captures'")], {}
    objects, captures = rec.get("objects"), rec.get("captures")
    if not (isinstance(objects, list) and isinstance(captures, list)
            and all(isinstance(x, str) and x for x in objects + captures)):
        return [Problem(MANIFEST_NAME, "corrupt: real.objects and real.captures must be lists of names")], {}
    records = manifest["shards"]
    files = [r["file"] for r in records]
    if len(set(files)) != len(files):
        out.append(Problem(MANIFEST_NAME, "shard list names a file twice"))
    if len(set(captures)) != len(captures):
        out.append(Problem(MANIFEST_NAME, "real.captures names a capture twice"))
    if len(set(objects)) != len(objects):
        out.append(Problem(MANIFEST_NAME, "real.objects names an object twice"))
    n_images = sum(int(r["n_images"]) for r in records)
    for key, want, what in (("n_images", n_images, "the shards hold"), ("n_images", len(captures), "real.captures lists"),
                            ("n_objects", len(objects), "real.objects lists"),
                            ("n_shards_expected", len(records), "the shard list has")):
        if manifest[key] != want:
            out.append(Problem(MANIFEST_NAME, f"{key} is {manifest[key]} but {what} {want}"))
    for key in ("class_name", "split", "seed"):
        if config is not None and manifest[key] != getattr(config, key):
            out.append(Problem(MANIFEST_NAME, f"{key} {manifest[key]!r} differs from its config's {getattr(config, key)!r}"))
    captures_of, offset = {}, 0
    for k, r in enumerate(records):
        if r["file"] != shard_name(k):
            out.append(Problem(MANIFEST_NAME, f"shard {k} is {r['file']!r}, expected {shard_name(k)}"))
        if not 0 <= r["object_start"] < r["object_stop"] <= len(objects):
            out.append(Problem(MANIFEST_NAME, f"{r['file']}: objects [{r['object_start']}, {r['object_stop']}) "
                                              f"outside the {len(objects)} objects of real.objects"))
        captures_of[r["file"]] = captures[offset:offset + int(r["n_images"])]
        offset += int(r["n_images"])
    if manifest["complete"] is not True:
        out.append(Problem(MANIFEST_NAME, "'complete' is not true (an ingest that did not finish)"))
    return out, (captures_of if offset == len(captures) else {})
