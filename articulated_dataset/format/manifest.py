"""The per-split manifest: what it holds (:class:`SplitConfig`, the shard records) and how it
is read and checked.

``OUT/<class>/<split>/manifest.json`` lists the split's complete shards (file, images,
bytes, sha256, object range) and the settings that determine its bytes (``config``: a
:class:`SplitConfig` as a dict).  The generator fills a :class:`SplitConfig`
(:class:`articulated_dataset.generation.pipeline.GenerationConfig` is one, with the checks that need the
class registry); reading one needs neither the generator nor MuJoCo.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from articulated_dataset import FORMAT_VERSION  # noqa: F401  (the default splits' version; schema.format_version_for)
from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.errors import DataFormatError, UserError, option
from articulated_dataset.core.safeio import atomic_write_bytes
from articulated_dataset.core.tables import SamplingTable
from articulated_dataset.format.schema import check_version
from articulated_dataset.format.shards import check_class_name, check_shard_file, read_json_object, resolve_inside

MANIFEST_NAME = "manifest.json"

#: Depth values are rounded to multiples of 2**-13 m (0.122 mm), far below any depth
#: sensor's resolution; it makes float32 depth compress ~3x better losslessly.
DEFAULT_DEPTH_QUANTUM_M = 2.0**-13
#: A moving part must cover at least this fraction of the image in every view
#: (0.2% = 41 px at 192x108); otherwise the object's pose is redrawn.
DEFAULT_MIN_PART_FRACTION = 0.002
DEFAULT_IMAGES_PER_OBJECT = 16
DEFAULT_OBJECTS_PER_SHARD = 64
DEFAULT_SEED = 0
#: Largest seed: shards store it as a signed 64-bit integer attribute.
MAX_SEED = 2**63 - 1
#: Scene context around the object (``--scene``; articulated_dataset.generation.scenes): none = the paper's isolated objects.
SCENE_NAMES = ("none", "kitchen", "room")
#: Most occluders per image (``--occluders``; articulated_dataset.generation.occluders).
MAX_OCCLUDERS = 8
#: Where an object may stand in the image (``--framing``; articulated_dataset.generation.framing):
#: table4 = the sampling table's ranges (the paper's Table 4), whole = the whole object in view.
FRAMINGS = ("table4", "whole")
DEFAULT_FRAMING = "table4"
#: Smallest image side (px) of ``--framing whole``: an interior inside the border rows and columns.
MIN_FRAMED_SIDE_PX = 3


@dataclass(frozen=True)
class SplitConfig:
    """Everything that determines a split's bytes: the manifest's ``config``.

    Its own checks need no class registry (counts, seed range, split name); the generator's
    :class:`~articulated_dataset.generation.pipeline.GenerationConfig` adds those that do.
    """

    class_name: str
    split: str = "train"
    n_objects: int = 100
    seed: int = DEFAULT_SEED
    images_per_object: int = DEFAULT_IMAGES_PER_OBJECT
    objects_per_shard: int = DEFAULT_OBJECTS_PER_SHARD
    camera: CameraConfig = field(default_factory=CameraConfig)
    table: SamplingTable | None = None  # None: the class's default table (filled by the generator)
    min_part_pixels: int | None = None  # None: DEFAULT_MIN_PART_FRACTION of the image
    depth_quantum_m: float = DEFAULT_DEPTH_QUANTUM_M
    mean: bool = False  # render the class's mean object (n_objects must be 1)
    noise: str = "none"  # depth sensor-noise model applied after rendering (articulated_dataset.core.noise)
    # Definition of a third-party URDF class (articulated_dataset.generation.urdf_import), rebuilt in
    # every worker process; None for registry classes.
    third_party: dict | None = None
    # Options beyond the paper's dataset: in the manifest only when used.
    scene: str = "none"  # scene context around the object (SCENE_NAMES)
    occluders: int = 0  # occluding shapes between the camera and the object, per image
    rgb: bool = False  # also store colour images (articulated_dataset.generation.appearance)
    framing: str = DEFAULT_FRAMING  # where an object may stand in the image (FRAMINGS)

    def __post_init__(self) -> None:
        self._validate()
        if self.min_part_pixels is None:
            area = self.camera.width_px * self.camera.height_px
            object.__setattr__(self, "min_part_pixels", int(math.ceil(DEFAULT_MIN_PART_FRACTION * area)))

    def _validate(self) -> None:
        """UserErrors for settings no split can have (the generator adds its class checks)."""
        if self.n_objects <= 0:
            raise UserError(f"number of objects must be positive, got {self.n_objects}")
        if self.images_per_object <= 0:
            raise UserError(f"images per object must be positive, got {self.images_per_object}")
        if self.objects_per_shard <= 0:
            raise UserError(f"objects per shard must be positive, got {self.objects_per_shard}")
        if not 0 <= self.seed <= MAX_SEED:
            raise UserError(f"seed must be in [0, 2**63 - 1] (it is stored as a 64-bit integer), got {self.seed}")
        if self.mean and self.n_objects != 1:
            raise UserError(f"{option('mean')} renders exactly one object (the class's mean object)")
        if not self.split or "/" in self.split or self.split.startswith(".") or not is_utf8(self.split):
            raise UserError(f"invalid split name {self.split!r}")
        if self.scene not in SCENE_NAMES:
            raise UserError(f"unknown scene {str(self.scene)[:40]!r}; choose from: {', '.join(SCENE_NAMES)}")
        if isinstance(self.occluders, bool) or not isinstance(self.occluders, int) or not 0 <= self.occluders <= MAX_OCCLUDERS:
            raise UserError(f"{option('occluders')} must be an integer in [0, {MAX_OCCLUDERS}], "
                            f"got {str(self.occluders)[:40]}")
        if not isinstance(self.rgb, bool):
            raise UserError(f"rgb must be true or false, got {str(self.rgb)[:40]}")
        self._validate_framing()
        if self.has_context:
            context = option("scene") if self.scene != "none" else option("occluders")
            if self.mean:
                raise UserError(f"{option('mean')} renders the class's isolated mean object; drop {context}")
            if self.third_party is not None and self.scene != "none":
                raise UserError(f"{option('scene')} places the built-in classes (docs/generation.md); a "
                                f"{option('urdf_path')} object takes {option('occluders')} only")

    def _validate_framing(self) -> None:
        """``--framing whole`` draws each object's pose for the fixed camera's empty view."""
        if self.framing not in FRAMINGS:
            raise UserError(f"unknown framing {str(self.framing)[:40]!r}; choose from: {', '.join(FRAMINGS)}")
        if self.framing == DEFAULT_FRAMING:
            return
        if self.mean:
            raise UserError(f"{option('mean')} renders the class's mean object at the centre of the table's "
                            f"ranges; drop {option('framing')} whole")
        if self.camera.mount != "fixed":
            raise UserError(f"{option('framing')} whole keeps the whole object in the fixed camera's view "
                            f"({option('camera_mount')} fixed); the head camera aims at the object itself")
        if self.has_context:
            raise UserError(f"{option('framing')} whole keeps the object alone in view; drop {option('scene')} and "
                            f"{option('occluders')}")
        if min(self.camera.width_px, self.camera.height_px) < MIN_FRAMED_SIDE_PX:
            side = MIN_FRAMED_SIDE_PX
            raise UserError(f"{option('framing')} whole needs an image of at least {side} x {side} px "
                            "(pixels inside the border rows and columns)")

    @property
    def has_context(self) -> bool:
        """Whether anything besides the object is rendered (``--scene`` or ``--occluders``):
        such splits store the occlusion fields (format version 1.1)."""
        return self.scene != "none" or self.occluders > 0

    @property
    def format_version(self) -> str:
        """The format version the split is written with
        (:func:`~articulated_dataset.format.schema.format_version_for`)."""
        from articulated_dataset.format.schema import format_version_for

        return format_version_for(self.has_context, self.rgb)

    @property
    def n_shards(self) -> int:
        """Number of shards: ``n_objects / objects_per_shard``, rounded up."""
        return -(-self.n_objects // self.objects_per_shard)

    def shard_objects(self, shard_index: int) -> range:
        """Object indices written to shard ``shard_index``."""
        start = shard_index * self.objects_per_shard
        return range(start, min(start + self.objects_per_shard, self.n_objects))

    def to_dict(self) -> dict:
        """The configuration as recorded in the manifest: plain JSON types, the format version added, and the scene,
        occluder, colour and framing options left out at their defaults."""
        d = asdict(self)
        d["camera"] = self.camera.to_dict()  # options beyond the paper's camera only when set
        d["table"] = self.table.to_dict()  # type: ignore[union-attr]  # filled in before a manifest is written
        d["format_version"] = self.format_version
        for key, default in (("scene", "none"), ("occluders", 0), ("rgb", False),
                             ("framing", DEFAULT_FRAMING)):  # a default split's manifest is as it was
            if d[key] == default:
                del d[key]
        return d

    @classmethod
    def from_dict(cls, d: dict):
        """The inverse of :meth:`to_dict`: UserError for invalid settings, KeyError/TypeError/
        ValueError for a malformed dict (:func:`split_config` turns both into one line)."""
        d = {k: v for k, v in d.items() if k != "format_version"}
        d["camera"] = CameraConfig(**d["camera"])
        d["table"] = SamplingTable.from_dict(d["table"])
        return cls(**d)

    def as_split_config(self) -> "SplitConfig":
        """The same settings as a plain :class:`SplitConfig` (drops a subclass's behaviour)."""
        return SplitConfig(**{f.name: getattr(self, f.name) for f in fields(SplitConfig)})


def split_config(manifest: dict, where: str = "") -> SplitConfig:
    """The manifest's ``config`` as a :class:`SplitConfig`; a missing, malformed or invalid
    config is one :class:`DataFormatError` naming ``where``."""
    prefix = f"{where}: " if where else ""
    config = manifest.get("config")
    if not isinstance(config, dict):
        raise DataFormatError(f"{prefix}corrupt manifest (no config object)")
    try:
        return SplitConfig.from_dict(config)
    except UserError as exc:
        raise DataFormatError(f"{prefix}invalid generation config ({exc.message})") from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise DataFormatError(f"{prefix}corrupt generation config ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0][:200] if str(exc) else ''})") from None


def is_utf8(text: str) -> bool:
    """``text`` encodes as UTF-8 (a command-line argument or file name that was not UTF-8
    arrives holding lone surrogates, which no seed hash, JSON file or HDF5 attribute can store)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


#: Keys of a third-party definition (the ``third_party`` entry of a generation config) that name
#: files by absolute path: the URDF, and the folder its meshes are read from where one was given.
THIRD_PARTY_PATH_KEYS = ("urdf", "mesh_root")


def third_party_definition(config, split_dir: str | Path | None) -> dict | None:
    """The third-party URDF definition (``generate --urdf``) of a manifest's ``config`` dict,
    None for a built-in class; one that is not an object is a :class:`DataFormatError`."""
    definition = config.get("third_party") if isinstance(config, dict) else None
    if definition is not None and not isinstance(definition, dict):
        raise DataFormatError(f"{split_dir}: corrupt third-party URDF definition (the 'third_party' entry of the "
                              "generation config is not an object)")
    return definition


def check_stored_object_files(config, split_dir: str | Path | None, what: str, hint: str = "") -> None:
    """Refuse (one line) to rebuild a stored third-party object from files outside its split folder.

    A split generated with ``--urdf`` records its URDF (and ``--mesh-root``) by absolute path in the
    manifest's ``config`` (``config``: that dict).  Rebuilding the object (``what``: ``show --rgb``,
    ``plan``, the ICP baseline's mean object) would open those files, and whether they are the
    ones the split was generated from shows only once they are read (their sha256).  A path read
    from data is opened only inside the folder the user named, so one outside ``split_dir`` (the
    usual case: the URDF stays where it was imported from) is refused before anything is opened;
    ``split_dir`` None (no folder named) refuses every third-party object.  ``hint`` ends the
    message.  Built-in classes rebuild from the package's own templates: nothing to check.
    The caller may instead name the files to rebuild from itself
    (:func:`~articulated_dataset.generation.objects.stored_object_config`)."""
    definition = third_party_definition(config, split_dir)
    if definition is None:
        return
    base = None if split_dir is None else Path(split_dir).resolve()
    for key in THIRD_PARTY_PATH_KEYS:
        value = definition.get(key)
        if value is None and key != "urdf":
            continue
        inside = base is not None and isinstance(value, str) and "\0" not in value and Path(value).is_absolute()
        if inside:
            try:
                real = Path(value).resolve()  # type: ignore[arg-type]  # inside: value is a str
            except (OSError, RuntimeError):  # a symbolic-link loop
                inside = False
            else:
                inside = real != base and real.is_relative_to(base)  # type: ignore[arg-type]  # inside: base is set
        if not inside:
            raise UserError(f"{split_dir or 'the split'}: a third-party URDF object (generate {option('urdf_path')}) "
                            f"whose {key} {str(value)[:120]!r} lies outside the split folder; {what} would rebuild "
                            f"it from those files, and paths read from data are opened only inside the folder "
                            f"given{hint}")


def printable(text) -> str:
    """``text`` with every character that is not printable (newline, carriage return, tab,
    escape and the other control characters, lone surrogates) written as its Python escape
    (``\\n``, ``\\x1b``...).  Names read from data (split, joint and size-class names, folder
    names) pass through it before they reach a terminal: a crafted name can neither start a new
    line nor send the terminal a control sequence."""
    text = str(text)
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def check_manifest_names(manifest: dict, where: str) -> dict:
    """Check the names a manifest gives to paths: its ``class_name`` and every shard's
    ``file``.  Returns ``manifest``; raises :class:`DataFormatError` naming ``where``."""
    if "class_name" not in manifest:
        raise DataFormatError(f"{where}: corrupt manifest (no class_name)")
    check_class_name(manifest["class_name"], where)
    records = manifest.get("shards")
    if not isinstance(records, list) or not all(isinstance(r, dict) and "file" in r for r in records):
        raise DataFormatError(f"{where}: corrupt manifest (shards must be a list of records with a 'file')")
    for r in records:
        check_shard_file(r["file"], where)
        n = r.get("n_images", 0)
        if not isinstance(n, int) or isinstance(n, bool) or n < 0:
            raise DataFormatError(f"{where}: corrupt manifest ({r['file']}: n_images must be a count, got {str(n)[:40]!r})")
    files = [r["file"] for r in records]
    if len(set(files)) != len(files):  # readers would serve that shard's images twice
        twice = next(f for f in files if files.count(f) > 1)
        raise DataFormatError(f"{where}: corrupt manifest (shard {twice} is listed twice; run 'artdata verify')")
    return manifest


def read_manifest(split_dir: str | Path) -> dict:
    """The manifest of ``split_dir``: version, names and shard paths checked."""
    split_dir = Path(split_dir)
    path = split_dir / MANIFEST_NAME
    if not path.is_file():
        raise DataFormatError(f"{split_dir}: no {MANIFEST_NAME} (not a generated split folder)")
    manifest = read_json_object(path, "manifest")
    check_version(manifest.get("format_version", "?"), str(path))
    check_manifest_names(manifest, str(path))
    if not isinstance(manifest.get("complete", True), bool):  # text such as "no" would read as true
        raise DataFormatError(f"{path}: field 'complete' is {str(manifest['complete'])[:20]!r}, not true or false")
    shard_paths(split_dir, manifest)  # every shard path stays inside the folder (no links leading out)
    return manifest


def shard_paths(split_dir: str | Path, manifest: dict) -> list[Path]:
    """The paths of a manifest's shards, each checked to be a shard name inside ``split_dir``."""
    where = str(Path(split_dir) / MANIFEST_NAME)
    return [resolve_inside(split_dir, check_shard_file(rec["file"], where), where=where) for rec in manifest["shards"]]


def write_manifest(split_dir: str | Path, manifest: dict) -> None:
    """Write ``manifest`` as ``split_dir/manifest.json`` (sorted keys, one-space indent) atomically
    (:func:`articulated_dataset.core.safeio.atomic_write_bytes`: readers see the old or the new file)."""
    atomic_write_bytes(Path(split_dir) / MANIFEST_NAME, (json.dumps(manifest, indent=1, sort_keys=True) + "\n").encode())
