"""Image and camera files read from outside the package: PNG and OpenEXR files (:mod:`.exr`),
intrinsics (:mod:`.intrinsics`) and the resampling of a capture onto the training camera
(:mod:`.resample`); the capture readers built on them are :mod:`articulated_dataset.ingest.readers`.  Every reader checks its
header before decoding (docs/security.md).
"""
