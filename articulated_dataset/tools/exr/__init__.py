"""OpenEXR interchange: export shards to per-image files and import them back exactly.

Layout of an exported split (``OUT/<class>/<split>/``, mirroring the shard layout)::

    split.json                 index: format, field table, source manifest, per-shard
                               attributes / K / R and the ordered list of image stems
    o000012_i003.exr           depth, float32, single channel "Z", metres, ZIP (lossless)
    o000012_i003.mask.png      mask, 8-bit greyscale PNG (values 0 .. 1 + J, lossless)
    o000012_i003.json          every label of the image (schema fields but depth/mask), K

The stem is ``o<object_index:06d>_i<image_index:03d>``.  Labels are written as JSON
numbers: a float32 value printed with Python's shortest round-trip repr and read back as
float64 then cast to float32 is the same float32, so labels, depth and mask round-trip
bit-exactly.  :func:`import_split` writes the shards with the same writer, attribute order
and manifest as the generator, so the re-imported shards are byte-identical files.

The modules: :mod:`.files` (the per-image files), :mod:`.export` (:func:`export_split`) and
:mod:`.restore` (:func:`import_split`, the index read back).
"""

from articulated_dataset.tools.exr.export import export_split
from articulated_dataset.tools.exr.restore import find_exports, import_split, import_tree, load_index, target_dir

__all__ = ["export_split", "find_exports", "import_split", "import_tree", "load_index", "target_dir"]
