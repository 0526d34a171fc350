"""The paper's mixture density network as a :class:`~articulated_dataset.methods.protocol.Method`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from articulated_dataset.core.errors import UserError, option
from articulated_dataset.methods.protocol import PredictSettings, TrainingInterrupted, TrainingRun, TrainSettings

if TYPE_CHECKING:
    from articulated_dataset.methods.mdn.checkpoint import MdnCheckpoint

#: Images per forward pass when predicting a split.
DEFAULT_PREDICT_BATCH = 256
#: Share of the training objects held out for validation when none is given.
DEFAULT_VAL_FRACTION = 0.1
#: The settings only the dense method uses.
DENSE_TRAIN_SETTINGS = ("width", "init_from", "origin_weight", "noise", "noise_fraction", "prompts")


class MdnMethod:
    """``--model mdn``: :mod:`articulated_dataset.methods.mdn`."""

    kind = "mdn"
    checkpoint_format = "artdata-mdn"
    single_image = False
    onnx_export = False

    def check_train_settings(self, settings: TrainSettings) -> None:
        """Refuse, in one line, the dense model's options, more than one split folder, and --mix-weights."""
        if settings.given(DENSE_TRAIN_SETTINGS):
            raise UserError(f"{option('width')}, {option('init_from')}, {option('origin_weight')}, {option('noise')}, "
                            f"{option('noise_fraction')} and {option('prompts')} belong to {option('model_kind')} dense")
        if len(settings.data) != 1:
            raise UserError(f"{option('model_kind')} mdn trains on one split; give one split folder "
                            f"({option('model_kind')} dense trains on several)")
        if settings.mix_weights is not None:
            raise UserError(f"{option('mix_weights')} belongs to {option('model_kind')} dense")

    def train(self, settings, *, resume, progress, echo):
        """Train an MDN with :func:`~.train.train` on the one split ``settings.data[0]`` into ``settings.out``;
        Ctrl-C raises :class:`TrainingInterrupted`."""
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
                                      f"same command plus {option('resume')}") from None
        return TrainingRun(ckpt, f"{ckpt['class_name']}, {ckpt['epoch']} epochs ({ckpt['data']['n_train']} training / "
                                 f"{ckpt['data']['n_val']} validation images)")

    def load_checkpoint(self, path: Path) -> MdnCheckpoint:
        """The MDN checkpoint at ``path``, read and checked."""
        from articulated_dataset.methods.mdn.checkpoint import load_checkpoint

        return load_checkpoint(path)

    def build_network(self, ckpt: MdnCheckpoint):
        """The MDN network of a checkpoint, in eval mode."""
        from articulated_dataset.methods.mdn.checkpoint import build_model_from_checkpoint

        return build_model_from_checkpoint(ckpt)

    def display_name(self, ckpt: MdnCheckpoint) -> str:
        """``MDN`` for the full preset, ``MDN-<preset>`` for another."""
        train_config = ckpt.get("train_config")
        preset = train_config.get("preset", "full") if isinstance(train_config, dict) else "full"
        return "MDN" if preset == "full" else f"MDN-{preset}"

    def check_predict_settings(self, settings: PredictSettings) -> None:
        """Refuse, in one line, the dense model's prediction options (--object-mask, --prompt, --no-mirror,
        --workers, --precision)."""
        if settings.object_mask:
            raise UserError(f"{option('object_mask')} applies to the dense model")
        if settings.prompt is not None:
            raise UserError(f"{option('prompt')} applies to the dense model")
        if not settings.mirror:
            raise UserError(f"{option('no_mirror')} applies to the dense model")
        if settings.workers is not None:
            raise UserError(f"{option('workers')} applies to the dense model (the MDN uses torch's threads)")
        if settings.precision != "float32":
            raise UserError(f"{option('precision')} applies to the dense "
                            "model (the MDN uses bfloat16 on a GPU by itself)")

    def predict_split(self, ref, data, settings, *, progress, as_class):
        """Predict every image of ``data`` with the MDN ``ref``: (method name, class name, arrays, file attributes)."""
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
