"""The data format: what a split folder holds and how to read it, with no generator.

* :mod:`.schema` -- every stored field (dtype, shape, units, frame), the mask codes, the joint
  types and the file-level dataset names;
* :mod:`.shards` -- names that may become paths, safe HDF5 opening, :class:`Shard`, and
  :func:`write_shard` (the one shard writer);
* :mod:`.manifest` -- the manifest and :class:`SplitConfig` (the settings that determine a
  split's bytes; the generator fills one), :func:`write_manifest`;
* :mod:`.discovery` -- finding ``<class>/<split>/`` folders;
* :mod:`.split` -- :class:`Split`, the one reader of a split folder.

Importing this package imports neither MuJoCo, OpenGL, torch nor jax.
"""

from articulated_dataset.format.discovery import find_split_dirs, find_splits, one_split_dir, splits_by_class
from articulated_dataset.format.manifest import (
    DEFAULT_DEPTH_QUANTUM_M,
    DEFAULT_IMAGES_PER_OBJECT,
    DEFAULT_MIN_PART_FRACTION,
    DEFAULT_OBJECTS_PER_SHARD,
    DEFAULT_SEED,
    MANIFEST_NAME,
    MAX_SEED,
    SplitConfig,
    check_manifest_names,
    read_manifest,
    shard_paths,
    split_config,
    write_manifest,
)
from articulated_dataset.format.schema import (
    FIELDS,
    FIELDS_BY_NAME,
    IMAGE_FIELDS,
    JOINT_TYPES,
    K_DATASET,
    LABEL_FIELDS,
    MASK_BACKGROUND,
    MASK_BODY,
    MASK_FIRST_PART,
    PRISMATIC,
    R_DATASET,
    REVOLUTE,
    ROOT_ATTRS,
    Field,
    check_version,
    object_on_border,
    resolve_shape,
    validate_arrays,
    visible_pixels,
)
from articulated_dataset.format.shards import (
    MAX_CLASS_NAME_CHARS,
    SHARD_PATTERN,
    TMP_SUFFIX,
    Shard,
    attr_value,
    check_class_name,
    check_h5_layout,
    check_shard_file,
    is_class_name,
    open_h5,
    read_json_object,
    reading,
    resolve_inside,
    sha256_file,
    shard_name,
    write_shard,
)
from articulated_dataset.format.split import Split, open_split

__all__ = [
    "DEFAULT_DEPTH_QUANTUM_M", "DEFAULT_IMAGES_PER_OBJECT", "DEFAULT_MIN_PART_FRACTION", "DEFAULT_OBJECTS_PER_SHARD",
    "DEFAULT_SEED", "FIELDS", "FIELDS_BY_NAME", "IMAGE_FIELDS", "JOINT_TYPES", "K_DATASET", "LABEL_FIELDS",
    "MANIFEST_NAME", "MASK_BACKGROUND", "MASK_BODY", "MASK_FIRST_PART", "MAX_CLASS_NAME_CHARS", "MAX_SEED",
    "PRISMATIC", "R_DATASET", "REVOLUTE", "ROOT_ATTRS", "SHARD_PATTERN", "TMP_SUFFIX", "Field", "Shard", "Split",
    "SplitConfig", "attr_value", "check_class_name", "check_h5_layout", "check_manifest_names", "check_shard_file",
    "check_version", "find_split_dirs", "find_splits", "is_class_name", "object_on_border", "one_split_dir", "open_h5",
    "open_split",
    "read_json_object", "read_manifest", "reading", "resolve_inside", "resolve_shape", "sha256_file", "shard_name",
    "shard_paths", "split_config", "splits_by_class", "validate_arrays", "visible_pixels", "write_manifest", "write_shard",
]
