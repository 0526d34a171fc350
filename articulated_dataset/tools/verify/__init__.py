"""Verify generated splits: manifest, checksums, file format and label invariants.

Every problem is reported as one line naming the file it was found in (``manifest.json``
or ``shard-NNNNN.h5``); nothing raises for bad data.  What is checked:

* **manifest**: readable JSON with the required keys, a readable format version and
  generation config; the shard list (each listed file exists, no unlisted shard file),
  per-shard byte sizes and sha256 checksums, and the counts (images, objects, shards;
  a split is complete when every expected shard is listed).
* **format** (per shard, via :mod:`articulated_dataset.format.schema`): readable HDF5, root
  attributes, every schema dataset with its declared dtype and shape, the ``K`` and
  ``R_camera_to_optical`` datasets, attributes consistent with the manifest.
* **content** (skipped with ``content=False``): finite values, and the label invariants

  - ``depth >= 0`` and a multiple of ``depth_quantum_m``; ``depth > 0`` exactly where
    ``mask > 0`` (noise-free data);
  - ``mask`` values in ``[0, 1 + J]``; ``visible_pixels`` equal to the mask's pixel counts
    and, for each moving part, at least ``min_part_pixels`` (sampled objects);
  - ``|axis_direction| = 1`` and the quaternions of ``axis_pose`` / ``object_pose``
    normalised (within :data:`UNIT_TOL`); ``axis_pose`` position = ``axis_origin`` and its
    z axis = ``axis_direction``;
  - ``q``, the object position and ``object_yaw`` within the sampling table's limits (root
    attribute ``sampling_table``); ``object_yaw`` = yaw of ``object_pose``; with a head
    camera (root attribute ``camera_mount``), the camera's pitch and roll read from the
    object's up axis within the head ranges and the object's level-frame pose within the
    table (:func:`articulated_dataset.generation.viewpoint.level_pose_from_camera`);
  - ``K`` equal to the image size's paper camera, or its ``intrinsics`` preset;
  - per-object labels identical over the object's images (only ``geometry`` with a head
    camera, which moves per image); ``object_index`` /
    ``image_index`` in generation order; ``sample_id`` equal to
    :func:`articulated_dataset.generation.sampling.sample_id` and unique over the split;
  - ``class`` = the shard's class; positive body dimensions; chirality 0 or 1.

**Real splits** (written by ``artdata ingest``: manifest key ``real``, shard attribute
``real = 1``) follow their own rules (docs/real_data.md): label values the capture does not
give are NaN (checked by :func:`articulated_dataset.ingest.ground_truth.real_label_problems`: never infinite,
NaN per group as a whole, q within the class's joint range, plausible positions and sizes);
``sample_id`` is :func:`articulated_dataset.ingest.write.real_sample_id` of the shard's
``capture_names``; objects and images are numbered by capture, not by generation order, and a
real object's pose differs between captures; the shard's K may be a crop's (it must be a
pinhole matrix agreeing with ``vfov_deg``); the manifest's counts come from its ``real``
record (objects, captures), not from a generation config.  Everything else (format,
checksums, depth, masks, unit vectors, frames) is checked as for generated data.

The modules: :mod:`.split` (find split folders, verify them, one :class:`SplitReport` each),
:mod:`.manifest` (manifest checks), :mod:`.shard` (one shard file: checksum, HDF5, attributes,
datasets) and :mod:`.content` (the label invariants).  Importing this package imports neither
MuJoCo, OpenGL, torch nor jax.
"""

from articulated_dataset.tools.verify.content import LIMIT_TOL, UNIT_TOL, quat_rotate_z
from articulated_dataset.tools.verify.manifest import Problem
from articulated_dataset.tools.verify.shard import ShardExpectation, check_shard
from articulated_dataset.tools.verify.split import SplitReport, count_shards, find_splits, verify_split, verify_splits

__all__ = ["Problem", "SplitReport", "ShardExpectation", "check_shard", "verify_split", "verify_splits", "find_splits",
           "count_shards", "quat_rotate_z", "UNIT_TOL", "LIMIT_TOL"]
