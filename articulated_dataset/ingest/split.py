"""Many captures into one real split, as ``artdata ingest`` does it.

:func:`ingest_split` finds the captures (:func:`~articulated_dataset.ingest.captures.find_captures`),
checks that the training camera and the captures fit in memory, ingests each
(:func:`~articulated_dataset.ingest.capture.ingest_capture`) and writes the split
(:func:`~articulated_dataset.ingest.write.write_real_split`).  :func:`camera_like` is the training
camera of an existing split (``--like``).
"""

from __future__ import annotations

from pathlib import Path

from articulated_dataset.core.camera import CameraConfig
from articulated_dataset.core.errors import UserError, option
from articulated_dataset.core.safeio import check_memory

#: Bytes per training-resolution pixel held per capture while ingesting: stored float32 depth
#: and uint8 mask, plus float64 depth and int64 index temporaries of the resampling.
BYTES_PER_PIXEL = 4 + 1 + 8 + 8


def camera_like(path: str) -> CameraConfig:
    """The camera of an existing split (its manifest's config)."""
    from articulated_dataset.format import find_split_dirs, read_manifest

    dirs = find_split_dirs(path)
    try:
        cam = read_manifest(dirs[0])["config"]["camera"]
        w, h, vfov = cam["width_px"], cam["height_px"], cam["vfov_deg"]
        if not (all(isinstance(v, int) and not isinstance(v, bool) for v in (w, h))
                and isinstance(vfov, (int, float)) and not isinstance(vfov, bool)):
            raise TypeError("camera values are not numbers")
        return CameraConfig(w, h, float(vfov))
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{option('like_path')} {path}: {dirs[0]}/manifest.json has no readable camera "
                        f"({type(exc).__name__}: {str(exc)[:80]})") from None


def check_training_camera(camera: CameraConfig) -> None:
    """One training image of ``camera`` fits in memory and its intrinsics are sane."""
    from articulated_dataset.core.images.intrinsics import check_intrinsics

    check_memory(float(camera.width_px) * camera.height_px * BYTES_PER_PIXEL,
                 f"a {camera.width_px}x{camera.height_px} training image")
    check_intrinsics(camera.K, (camera.width_px, camera.height_px),
                     f"training camera ({option('width')}/{option('height')}/{option('vfov')})")


def ingest_split(captures, class_name: str, out_root, options, *, split: str, mask_path=None, labels_path=None,
                 append: bool = False, overwrite: bool = False, progress: bool = True) -> tuple[Path, list]:
    """Ingest the captures named by ``captures`` (files or folders) with ``options``
    (:class:`~articulated_dataset.ingest.capture.IngestOptions`, its camera the training camera) into
    ``out_root/<class>/<split>/``; ``mask_path`` / ``labels_path`` name one capture's mask and
    labels files.  Returns the split folder and the ingested captures."""
    from tqdm import tqdm

    from articulated_dataset.ingest.capture import ingest_capture
    from articulated_dataset.ingest.captures import find_captures
    from articulated_dataset.ingest.write import write_real_split

    camera = options.camera
    files = find_captures(captures)
    if (mask_path or labels_path) and len(files) != 1:
        raise UserError(f"{option('mask_path')} and {option('labels_path')} name the files of one capture; "
                        f"{len(files)} captures were given")
    check_memory(float(len(files)) * camera.width_px * camera.height_px * BYTES_PER_PIXEL,
                 f"{len(files)} captures at {camera.width_px}x{camera.height_px} px")
    if mask_path:
        files[0].mask = Path(mask_path)
    if labels_path:
        files[0].labels = Path(labels_path)
    ingested = [ingest_capture(f, class_name, options) for f in tqdm(files, unit="capture", disable=not progress, desc="ingest")]
    split_dir = write_real_split(ingested, class_name, out_root, split=split, camera=camera, options=options,
                                 append=append, overwrite=overwrite)
    return split_dir, ingested
