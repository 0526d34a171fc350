"""The dense voting estimator as a :class:`~articulated_dataset.methods.protocol.Method`."""

from __future__ import annotations

from pathlib import Path

from articulated_dataset.core.errors import UserError
from articulated_dataset.methods.protocol import PredictSettings, TrainingInterrupted, TrainingRun, TrainSettings

#: Images per forward pass when predicting a split.
DEFAULT_PREDICT_BATCH = 128


class DenseMethod:
    """``--model dense``: :mod:`articulated_dataset.methods.dense`."""

    kind = "dense"
    checkpoint_format = "artdata-dense"
    single_image = True
    onnx_export = True

    def check_train_settings(self, settings: TrainSettings) -> None:
        if settings.given(("small", "components")):
            raise UserError("--small and --components belong to --model mdn")

    def train(self, settings, *, resume, progress, echo):
        from articulated_dataset.methods.dense.train import DenseTrainConfig, train_dense

        given = {"epochs": settings.epochs, "batch_size": settings.batch_size, "lr": settings.lr,
                 "width": settings.width, "val_fraction": settings.val_fraction,
                 "origin_weight": settings.origin_weight, "noise": settings.noise,
                 "noise_fraction": settings.noise_fraction}
        config = DenseTrainConfig(class_name=settings.class_name, max_objects=settings.max_objects, seed=settings.seed,
                                  init_from=settings.init_from, **{k: v for k, v in given.items() if v is not None})
        data = list(settings.data)
        mix = None if settings.mix_weights is None else list(settings.mix_weights)
        try:
            ckpt = train_dense(data, settings.out, config, resume=resume, progress=progress, echo=echo,
                               device=settings.device, mix_weights=mix)
        except KeyboardInterrupt:
            raise TrainingInterrupted(f"interrupted; the last checkpoint is in {settings.out}. Continue with the same "
                                      f"command plus --resume") from None
        return TrainingRun(ckpt, f"dense {ckpt['class_name']}, {ckpt['step']} steps ({ckpt['data']['n_train_images']} "
                                 f"training / {ckpt['data']['n_val_images']} validation images)")

    def load_checkpoint(self, path: Path) -> dict:
        from articulated_dataset.methods.dense.checkpoint import load_dense_checkpoint

        return load_dense_checkpoint(path)

    def build_network(self, ckpt: dict):
        from articulated_dataset.methods.dense.checkpoint import build_dense_model

        return build_dense_model(ckpt)

    def display_name(self, ckpt: dict) -> str:
        return "dense"

    def check_predict_settings(self, settings: PredictSettings) -> None:
        if settings.snap_to_cloud:
            raise UserError("--snap-to-cloud applies to MDN models; the dense model's origins are already point votes")
        if settings.estimate != "mean-of-best":
            raise UserError("--estimate applies to MDN models; the dense model always gives its heaviest vote mode")
        if settings.device not in ("auto", "cpu"):
            raise UserError(f"--device {settings.device}: the dense model runs on the CPU (--device applies to MDN "
                            f"models)")

    def predict_split(self, ref, data, settings, *, progress, as_class):
        from articulated_dataset.methods.dense.predict import predict_split

        ckpt = self.load_checkpoint(ref.path)
        name = settings.method or ref.name  # dense, dense-kinect2 (shipped) or dense (a checkpoint file)
        batch_size = DEFAULT_PREDICT_BATCH if settings.batch_size is None else settings.batch_size
        class_name, arrays = predict_split(ckpt, data, batch_size=batch_size, object_mask=settings.object_mask,
                                           mirror=settings.mirror, workers=settings.workers,
                                           precision=settings.precision, progress=progress, as_class=as_class)
        attrs = {"estimate": "heaviest-mode", "steps": int(ckpt["step"]), "object_mask": int(settings.object_mask),
                 "mirror": int(settings.mirror), "precision": settings.precision}
        return name, class_name, arrays, attrs


METHOD = DenseMethod()
