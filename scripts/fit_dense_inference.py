"""Refit the refinement choice and uncertainty calibration of finished dense checkpoints.

    python scripts/fit_dense_inference.py --checkpoint dense-C.pt --data data/C/train --out refit/dense-C.pt

Loads the checkpoint's training split, takes the validation objects that training held out
(same ``--val-fraction``, ``--seed`` and ``--max-objects``), chooses the geometric refinement
(:func:`articulated_dataset.methods.dense.fit.fit_refinement`) and refits the calibration on them
(:func:`articulated_dataset.methods.dense.predict.fit_inference`), and writes the checkpoint to
``--out``.  Training does this itself since the refinement exists; this script brings older
checkpoints (the shipped ones trained before it, or before a refinement version) up to date.
``--clean`` fits a model trained with ``--noise`` on the noise-free validation images (training
fits on the noisy ones).  ``--calibration-only`` keeps the refinement chosen before (the same point
estimates and modes) and refits the calibration alone: the modes' scales and the outlier
component.  Prints the validation errors of every candidate (with ``--calibration-only``: the
outlier component's weight and validation NLL).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True, help="finished dense checkpoint (artdata train --model dense)")
    p.add_argument("--data", required=True, help="its training split folder")
    p.add_argument("--out", required=True, help="checkpoint to write")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--clean", action="store_true",
                   help="fit on the noise-free validation images even where training used --noise "
                        "(a model trained with noise, fitted for noise-free depth)")
    p.add_argument("--calibration-only", action="store_true",
                   help="keep the checkpoint's refinement (its point estimates and modes) and refit only the "
                        "calibration: the modes' scales and the outlier component")
    args = p.parse_args(argv)
    if args.threads is not None and args.threads < 1:
        p.error(f"--threads must be positive, got {args.threads}")
    import torch

    from articulated_dataset.core.errors import UserError
    from articulated_dataset.methods.dense.train import refit_inference

    if args.threads:
        torch.set_num_threads(args.threads)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        result = refit_inference(args.checkpoint, args.data, args.out, clean=args.clean,
                                 calibration_only=args.calibration_only)
    except UserError as e:
        print(f"fit_dense_inference: error: {e}", file=sys.stderr)
        return 2
    report = {"class": result["class_name"], "refinement": result["refinement"],
              "outlier": {k: v for k, v in (result["calibration"].get("outlier") or {}).items() if k != "scale"}}
    if not args.calibration_only:
        report["validation"] = result["refinement_report"]
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
