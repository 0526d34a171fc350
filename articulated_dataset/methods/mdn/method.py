"""The paper's mixture density network as a :class:`~articulated_dataset.methods.protocol.Method`."""

from __future__ import annotations

from pathlib import Path

from articulated_dataset.core.errors import UserError
from articulated_dataset.methods.protocol import PredictSettings, TrainingInterrupted, TrainingRun, TrainSettings

#: Images per forward pass when predicting a split.
DEFAULT_PREDICT_BATCH = 256
#: Share of the training objects held out for validation when none is given.
DEFAULT_VAL_FRACTION = 0.1
#: The settings only the dense method uses.
DENSE_TRAIN_SETTINGS = ("width", "init_from", "origin_weight", "noise", "noise_fraction")


class MdnMethod:
    """``--model mdn``: :mod:`articulated_dataset.methods.mdn`."""

    kind = "mdn"
    checkpoint_format = "artdata-mdn"
    single_image = False
    onnx_export = False

    def check_train_settings(self, settings: TrainSettings) -> None:
        if settings.given(DENSE_TRAIN_SETTINGS):
            raise UserError("--width, --init-from, --origin-weight, --noise and --noise-fraction belong to --model dense")
        if len(settings.data) != 1:
            raise UserError("--model mdn trains on one split; give one split folder (--model dense trains on several)")
        if settings.mix_weights is not None:
            raise UserError("--mix-weights belongs to --model dense")

    def train(self, settings, *, resume, progress, echo):
        from articulated_dataset.methods.mdn.config import TrainConfig
        from articulated_dataset.methods.mdn.train import train

        val_fraction = DEFAULT_VAL_FRACTION if settings.val_fraction is None else settings.val_fraction
        config = TrainConfig(class_name=settings.class_name, preset="small" if settings.small else "full",
                             epochs=settings.epochs, batch_size=settings.batch_size, lr=settings.lr,
                             val_fraction=val_fraction, seed=settings.seed, n_components=settings.components,
                             max_objects=settings.max_objects)
        try:
            ckpt = train(settings.data[0], settings.out, config, device=settings.device, resume=resume,
                         progress=progress, echo=echo)
        except KeyboardInterrupt:
            raise TrainingInterrupted(f"interrupted; the last finished epoch is in {settings.out}. Continue with the "
                                      f"same command plus --resume") from None
        return TrainingRun(ckpt, f"{ckpt['class_name']}, {ckpt['epoch']} epochs ({ckpt['data']['n_train']} training / "
                                 f"{ckpt['data']['n_val']} validation images)")

    def load_checkpoint(self, path: Path) -> dict:
        from articulated_dataset.methods.mdn.checkpoint import load_checkpoint

        return load_checkpoint(path)

    def build_network(self, ckpt: dict):
        from articulated_dataset.methods.mdn.checkpoint import build_model_from_checkpoint

        return build_model_from_checkpoint(ckpt)

    def display_name(self, ckpt: dict) -> str:
        """``MDN`` for the full preset, ``MDN-<preset>`` for another."""
        train_config = ckpt.get("train_config")
        preset = train_config.get("preset", "full") if isinstance(train_config, dict) else "full"
        return "MDN" if preset == "full" else f"MDN-{preset}"

    def check_predict_settings(self, settings: PredictSettings) -> None:
        if settings.object_mask:
            raise UserError("--object-mask applies to the dense model")
        if not settings.mirror:
            raise UserError("--no-mirror applies to the dense model")
        if settings.workers is not None:
            raise UserError("--workers applies to the dense model (the MDN uses torch's threads)")
        if settings.precision != "float32":
            raise UserError("--precision applies to the dense model (the MDN uses bfloat16 on a GPU by itself)")

    def predict_split(self, ref, data, settings, *, progress, as_class):
        from articulated_dataset.methods.mdn.predict import predict_split

        ckpt = self.load_checkpoint(ref.path)
        preset = ckpt["train_config"].get("preset", "full")
        name = settings.method or self.display_name(ckpt)
        batch_size = DEFAULT_PREDICT_BATCH if settings.batch_size is None else settings.batch_size
        class_name, arrays = predict_split(ref.path, data, estimate=settings.estimate,
                                           snap_to_cloud=settings.snap_to_cloud, batch_size=batch_size,
                                           device=settings.device, progress=progress, as_class=as_class)
        attrs = {"estimate": settings.estimate, "snap_to_cloud": int(settings.snap_to_cloud),
                 "epochs": int(ckpt["epoch"]), "preset": preset}
        return name, class_name, arrays, attrs


METHOD = MdnMethod()
