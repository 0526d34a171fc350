"""Start a dense model of one class from another class's trained weights (transfer learning).

    python scripts/transplant_dense.py --from dense-cabinet2.pt --like dense-cabinet.pt --out init-cabinet.pt
    artdata train --model dense --class cabinet --data DIR --out dense-cabinet.pt --init-from init-cabinet.pt ...

``--from``: a dense checkpoint of the source class (e.g. the shipped two-door cabinet:
``artdata models --json`` names the files in ``articulated_dataset/methods/weights``); ``--like``: a
dense checkpoint of the target class with the same architecture (its class, joints, model
configuration and ``q`` loss scale are kept; its weights are not used).  The result holds the
source's weights: the whole network but the last 1x1 layer, and of that layer the rows that
mean the same in both classes -- the body's and the first parts' segmentation, the first joints'
16 channels each, and the geometry's 5 -- (rows without a source keep the target's).  It is a
checkpoint ``artdata train --init-from`` continues from; its ``transplant`` field names both
files by SHA-256 (``scripts/ship_weights.py`` records it in the lineage).

The shipped cabinet starts this way from the shipped two-door cabinet (whose doors are cabinet
doors of half the width): 4 epochs from it score better than 7 from the cabinet's own weights
(docs/dense.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from articulated_dataset.format import sha256_file
from articulated_dataset.methods.dense.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, build_dense_model
from articulated_dataset.methods.dense.model import GEOMETRY_CHANNELS, JOINT_CHANNELS
from articulated_dataset.methods.dense.train import load_dense_checkpoint


def head_rows(n_joints_src: int, n_joints_dst: int) -> tuple[list[int], list[int]]:
    """(source rows, target rows) of the last layer's outputs that mean the same in both classes
    (:meth:`~articulated_dataset.methods.dense.model.DenseNet.split`'s layout)."""
    J = min(n_joints_src, n_joints_dst)
    src, dst = list(range(1 + J)), list(range(1 + J))  # body, parts 0..J-1
    for j in range(J):
        src += [1 + n_joints_src + j * JOINT_CHANNELS + c for c in range(JOINT_CHANNELS)]
        dst += [1 + n_joints_dst + j * JOINT_CHANNELS + c for c in range(JOINT_CHANNELS)]
    src += [1 + n_joints_src + n_joints_src * JOINT_CHANNELS + c for c in range(GEOMETRY_CHANNELS)]
    dst += [1 + n_joints_dst + n_joints_dst * JOINT_CHANNELS + c for c in range(GEOMETRY_CHANNELS)]
    return src, dst


def transplant(src_ckpt: dict, like_ckpt: dict) -> dict:
    """The checkpoint of ``like_ckpt``'s class holding ``src_ckpt``'s weights (module docstring)."""
    s = build_dense_model(src_ckpt).state_dict()
    d = build_dense_model(like_ckpt).state_dict()
    rows_src, rows_dst = head_rows(len(src_ckpt["joint_types"]), len(like_ckpt["joint_types"]))
    out = {}
    for k, v in d.items():
        w = s[k]
        if k.startswith("head."):
            w = v.clone()
            w[rows_dst] = s[k][rows_src].to(v.dtype)
        elif w.shape != v.shape:
            raise SystemExit(f"transplant: {k} has shape {tuple(w.shape)} in the source and {tuple(v.shape)} in the "
                             f"target (give checkpoints of the same --width)")
        out[k] = w.clone()
    return {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "class_name": like_ckpt["class_name"],
            "joint_types": list(like_ckpt["joint_types"]), "model_config": dict(like_ckpt["model_config"]),
            "q_scale": list(like_ckpt["q_scale"]), "train_config": {}, "model_state": out, "finished": True,
            "step": 0, "history": []}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--from", dest="src", type=Path, required=True, help="dense checkpoint of the source class")
    p.add_argument("--like", type=Path, required=True, help="dense checkpoint of the target class (same --width)")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    src, like = load_dense_checkpoint(args.src), load_dense_checkpoint(args.like)
    ckpt = transplant(src, like)
    ckpt["transplant"] = {"from": {"file": args.src.name, "class_name": src["class_name"], "sha256": sha256_file(args.src)},
                          "like": {"file": args.like.name, "class_name": like["class_name"], "sha256": sha256_file(args.like)}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".partial")
    torch.save(ckpt, tmp)
    tmp.replace(args.out)
    print(f"{args.out}: {like['class_name']} weights from {src['class_name']} ({args.src.name})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
