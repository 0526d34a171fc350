"""Real captures -> shards: ingest depth images or point clouds from a real sensor.

One *capture* is one depth observation of one object:

* depth: a 16-bit PNG in millimetres, a float EXR in metres (channel ``Z``, ``depth``, ``Y``,
  ``R`` or the only channel) or a ``.npy`` array in metres; or a point cloud (``.ply`` via
  trimesh, ``.pcd`` ASCII/binary) rasterised with the intrinsics (nearest point per pixel);
* intrinsics: fx, fy, cx, cy (OpenCV, pixel centres at integer coordinates) from options or a
  camera-info file (JSON/YAML: ``fx/fy/cx/cy``, ROS ``CameraInfo`` ``K``/``k``, or a ROS
  calibration file's ``camera_matrix``; ``width``/``height`` or ``image_width``/``image_height``);
* optional segmentation mask PNG of the same size: binary (0/255 or 0/1: object = body, label 1)
  or the dataset's labels (0 background, 1 body, 2 + j moving part j);
* optional ground truth JSON (:func:`.ground_truth.load_ground_truth`), or the parts' poses and
  masks (:func:`.part_annotations.load_part_pose_ground_truth`).

Each capture is resampled to the training camera (:func:`.resample.resample_depth`): by default onto
exactly the training intrinsics (``fit="training"``: every training pixel reads its ray's
source pixel), or by cropping a window of the training aspect ratio around the mask and
scaling it to the training resolution (``fit="crop"``: K is rescaled; the shard stores it).
Depth is never interpolated: nearest neighbour, or the minimum depth of the source pixels
under the training pixel (``resample="min"``).  Outside a given mask the depth is set to 0,
as in the rendered training images (which have no background).

Labels a capture lacks are NaN (float fields) - see docs/real_data.md for the full list.

The modules, one job each:

* :mod:`.captures` -- finding captures and the files beside them;
* :mod:`.intrinsics` -- intrinsics from options or camera-info files, and their checks;
* :mod:`.readers` -- depth, mask and point-cloud files;
* :mod:`.resample` -- resampling to the training camera;
* :mod:`.ground_truth` -- the labels JSON and the checks of a real image's labels;
* :mod:`.part_annotations` -- ground truth from part poses (``NAME.parts.json`` and the object
  metadata file), with :mod:`.part_poses` (joint labels from two parts' poses) and
  :mod:`.coco_masks` (COCO polygon and RLE masks);
* :mod:`.ingest` -- one capture in, one training-resolution image out (:func:`.ingest.ingest_capture`);
* :mod:`.write` -- ingested captures written as a split (:func:`.write.write_real_split`).

This package imports none of its modules: import the one you need.  The depth-sensor noise
models applied to rendered depth (``kinect2``, ``d435``, ``azure-kinect``) are in
:mod:`articulated_dataset.core.noise`.
"""
