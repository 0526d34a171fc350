"""``articulated_dataset.load_model``: a shipped model or a checkpoint as a ready Python object.

    import articulated_dataset as ad

    model = ad.load_model("dense", "microwave")        # or a checkpoint: ad.load_model("run/dense-microwave.pt")
    est = model.estimate(depth_m, K)                    # one (H, W) depth image (m) and its 3x3 intrinsics
    arrays = model.predict("data/microwave/test")      # every image of a split: the predictions file's arrays

:meth:`LoadedModel.estimate` is :func:`articulated_dataset.estimate` (the same checks, resampling,
network, vote modes and refinement) with this model; :meth:`LoadedModel.predict` is ``artdata
predict`` (:func:`~.predict.predict_to_file`).  Both import torch; loading reads and checks the
checkpoint once (a shipped model's files against their SHA-256) and, for the dense model, builds
its inference network.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.protocol import get_method


@dataclass(frozen=True)
class LoadedModel:
    """A model ready to use (built by :func:`load_model`).

    ``spec``: what was asked for (a shipped model's name or a checkpoint path); ``name``: its
    display name (``dense``, ``dense-kinect2``, ``mdn-small``, ``MDN``...); ``kind``: ``"dense"``
    or ``"mdn"``; ``class_name`` and ``joint_types``: the object class it estimates; ``path``: its
    checkpoint file; ``checkpoint``: the checked checkpoint (configuration, calibration,
    refinement, weights)."""

    spec: str
    name: str
    kind: str
    class_name: str
    joint_types: tuple
    path: Path
    checkpoint: dict = field(repr=False)

    def estimate(self, depth_m, K, mask=None, *, mirror: bool = True, precision: str = "float32"):
        """The :class:`~.estimation.Estimate` of one depth image: ``depth_m`` (H, W) z-depth in
        metres (0 or NaN: no return), ``K`` its 3x3 intrinsics (OpenCV convention), ``mask`` an
        optional (H, W) boolean object mask; ``mirror`` and ``precision`` as for
        :func:`articulated_dataset.estimate`.  Results are in the image's camera frame (x forward,
        y left, z up), metres and radians.  Dense models only (an MDN predicts splits: :meth:`predict`);
        bad input is a :class:`~articulated_dataset.core.errors.UserError`."""
        from articulated_dataset.methods.estimation import estimate

        self._need_dense()
        return estimate(depth_m, K, self.class_name, mask=mask, model=self.spec, mirror=mirror, precision=precision)

    def estimate_file(self, depth_path, *, camera_path=None, mask_path=None, depth_units: str = "auto",
                      mirror: bool = True, precision: str = "float32"):
        """:meth:`estimate` of a depth file, as ``artdata estimate`` reads it: a 16-bit PNG in
        millimetres, an EXR or a .npy in metres (``depth_units`` overrides), its camera file
        (default: ``NAME.camera.json`` or ``camera.json`` beside it) and an optional mask PNG
        (:func:`~.estimation.estimate_file`)."""
        from articulated_dataset.methods.estimation import estimate_file

        self._need_dense()
        return estimate_file(depth_path, self.class_name, camera_path=camera_path, mask_path=mask_path,
                             depth_units=depth_units, model=self.spec, mirror=mirror, precision=precision)

    def predict(self, data, out=None, **options) -> dict:
        """Predict every image of the split folder ``data`` (``artdata predict``); returns the
        arrays of the predictions file (``{dataset: array}``: ``sample_id``, ``axis_pose``,
        ``q``, ``geometry``, the mixture..., as
        :func:`articulated_dataset.benchmark.predictions.read_predictions` reads them), and keeps
        the file at ``out`` where given (for ``artdata score``).  ``options``: the keywords of
        :func:`~.predict.predict_to_file` (``batch_size``, ``mirror``, ``precision``, ``object_mask``,
        ``workers`` for the dense model; ``estimate``, ``snap_to_cloud``, ``device`` for an MDN;
        ``as_class``, ``method``, ``progress``).  A split of another class is a
        :class:`~articulated_dataset.core.errors.UserError`."""
        from articulated_dataset.benchmark.predictions import read_predictions
        from articulated_dataset.methods.predict import predict_to_file

        options.setdefault("method", self.name)
        with tempfile.TemporaryDirectory(prefix="artdata-predict-") as tmp:
            target = Path(tmp) / "predictions.h5" if out is None else Path(out)
            # the checkpoint file, not the shipped name: a shipped name would pick the split's class's model
            run = predict_to_file(str(self.path), data, target, **options)
            _, per_class = read_predictions(target)
        return per_class[run.class_name]

    def network(self):
        """The model's PyTorch network in eval mode, its weights loaded (the dense model's
        :class:`~.dense.model.DenseNet`, not folded; an MDN's network)."""
        return get_method(self.kind).build_network(self.checkpoint)

    def _need_dense(self) -> None:
        if not get_method(self.kind).single_image:
            raise UserError(f"{self.name}: single-image estimates use a dense model (the shipped 'dense' or a 'artdata "
                            f"train {option('model_kind')} dense' checkpoint); "
                            "predict splits with an MDN: .predict(split)")


def load_model(name: str | Path, class_name: str | None = None) -> LoadedModel:
    """A shipped model (``name``: ``"dense"``, ``"dense-kinect2"`` or ``"mdn-small"``, with its
    ``class_name``) or a checkpoint file (``name``: a ``.pt`` from ``artdata train``, or a
    ``.safetensors`` with its ``.json``; ``class_name``, where given, must be the file's) as a
    :class:`LoadedModel`.  An unknown name or class, a missing, damaged or foreign file is a
    :class:`~articulated_dataset.core.errors.UserError`; without PyTorch, a ModuleNotFoundError that
    says how to install it."""
    from articulated_dataset.classes.registry import get_class
    from articulated_dataset.core.errors import import_optional
    from articulated_dataset.methods.shipped import load_model_checkpoint, resolve_model
    from articulated_dataset.training.loaders.reader import TORCH_INSTALL

    import_optional("torch", "articulated_dataset.load_model", TORCH_INSTALL, user_error=False)
    spec = str(name) if isinstance(name, Path) else name
    ref = resolve_model(spec, class_name)
    if get_method(ref.kind).single_image:  # read, checked and its inference network built and cached, as estimate() does
        from articulated_dataset.methods import estimation

        ckpt, _network, _name = estimation._load(spec, ref.class_name)
    else:
        ckpt = load_model_checkpoint(ref)
    return LoadedModel(spec, ref.name, ref.kind, ref.class_name, tuple(get_class(ref.class_name).joint_types),
                       ref.path, ckpt)
