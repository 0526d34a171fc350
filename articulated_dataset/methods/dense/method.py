"""The dense voting estimator as a :class:`~articulated_dataset.methods.protocol.Method`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.protocol import PredictSettings, TrainingInterrupted, TrainingRun, TrainSettings

if TYPE_CHECKING:
    from articulated_dataset.methods.dense.checkpoint import DenseCheckpoint

#: Images per forward pass when predicting a split.
DEFAULT_PREDICT_BATCH = 128
#: The predictions file's ``prompt`` attribute of a split predicted without ``--prompt`` or
#: ``--object-mask``: the model read every pixel with depth.
NO_PROMPT = "every-pixel"


class DenseMethod:
    """``--model dense``: :mod:`articulated_dataset.methods.dense`."""

    kind = "dense"
    checkpoint_format = "artdata-dense"
    single_image = True
    onnx_export = True

    def check_train_settings(self, settings: TrainSettings) -> None:
        """Refuse, in one line, the MDN options ``--small`` and ``--components``."""
        if settings.given(("small", "components")):
            raise UserError(f"{option('small')} and {option('components')} belong to {option('model_kind')} mdn")

    def train(self, settings, *, resume, progress, echo):
        """Train a dense model with :func:`~.train.train_dense` on ``settings.data`` into ``settings.out``; Ctrl-C
        raises :class:`TrainingInterrupted`."""
        from articulated_dataset.methods.dense.train import DenseTrainConfig, train_dense

        given = {"epochs": settings.epochs, "batch_size": settings.batch_size, "lr": settings.lr,
                 "width": settings.width, "val_fraction": settings.val_fraction,
                 "origin_weight": settings.origin_weight, "noise": settings.noise,
                 "noise_fraction": settings.noise_fraction, "prompts": settings.prompts}
        config = DenseTrainConfig(class_name=settings.class_name, max_objects=settings.max_objects, seed=settings.seed,
                                  init_from=settings.init_from, **{k: v for k, v in given.items() if v is not None})
        data = list(settings.data)
        mix = None if settings.mix_weights is None else list(settings.mix_weights)
        try:
            ckpt = train_dense(data, settings.out, config, resume=resume, progress=progress, echo=echo,
                               device=settings.device, mix_weights=mix)
        except KeyboardInterrupt:
            raise TrainingInterrupted(f"interrupted; the last checkpoint is in {settings.out}. Continue with the same "
                                      f"command plus {option('resume')}") from None
        return TrainingRun(ckpt, f"dense {ckpt['class_name']}, {ckpt['step']} steps ({ckpt['data']['n_train_images']} "
                                 f"training / {ckpt['data']['n_val_images']} validation images)")

    def load_checkpoint(self, path: Path) -> DenseCheckpoint:
        """The dense checkpoint at ``path``, read and checked."""
        from articulated_dataset.methods.dense.checkpoint import load_dense_checkpoint

        return load_dense_checkpoint(path)

    def build_network(self, ckpt: DenseCheckpoint):
        """The dense network of a checkpoint, in eval mode."""
        from articulated_dataset.methods.dense.checkpoint import build_dense_model

        return build_dense_model(ckpt)

    def display_name(self, ckpt: dict) -> str:
        """``dense``: the method's name in predictions files."""
        return "dense"

    def check_predict_settings(self, settings: PredictSettings) -> None:
        """Refuse, in one line, the MDN prediction options (--snap-to-cloud, --estimate, a --device other than auto
        or cpu), an unknown prompt, and --object-mask with a prompt other than mask."""
        from articulated_dataset.methods.prompts import PROMPT_KINDS

        if settings.prompt is not None and settings.prompt not in PROMPT_KINDS:
            raise UserError(f"{option('prompt')} must be one of {', '.join(PROMPT_KINDS)}, got {settings.prompt!r}")
        if settings.object_mask and settings.prompt not in (None, "mask"):
            raise UserError(f"{option('object_mask')} is {option('prompt')} mask; give one of them, not "
                            f"{option('prompt')} {settings.prompt} too")
        if settings.snap_to_cloud:
            raise UserError(f"{option('snap_to_cloud')} applies to MDN models; the dense model's origins are already "
                            "point votes")
        if settings.estimate != "mean-of-best":
            raise UserError(f"{option('estimate')} applies to MDN models; the dense model always gives its heaviest "
                            "vote mode")
        if settings.device not in ("auto", "cpu"):
            raise UserError(f"{option('device')} {settings.device}: the dense model runs on the CPU "
                            f"({option('device')} applies to MDN models)")

    def predict_split(self, ref, data, settings, *, progress, as_class):
        """Predict every image of ``data`` with the dense model ``ref``: (method name, class name, arrays, file
        attributes)."""
        from articulated_dataset.methods.dense.predict import predict_split

        ckpt = self.load_checkpoint(ref.path)
        name = settings.method or ref.name  # dense, dense-kinect2 (shipped) or dense (a checkpoint file)
        batch_size = DEFAULT_PREDICT_BATCH if settings.batch_size is None else settings.batch_size
        prompt = "mask" if settings.object_mask else settings.prompt  # None: every pixel with depth
        class_name, arrays = predict_split(ckpt, data, batch_size=batch_size, object_mask=settings.object_mask,
                                           mirror=settings.mirror, workers=settings.workers,
                                           precision=settings.precision, progress=progress, as_class=as_class,
                                           prompt=prompt)
        attrs = {"estimate": "heaviest-mode", "steps": int(ckpt["step"]), "object_mask": int(prompt == "mask"),
                 "prompt": prompt or NO_PROMPT,
                 "mirror": int(settings.mirror), "precision": settings.precision}
        return name, class_name, arrays, attrs


METHOD = DenseMethod()
