#!/usr/bin/env python3
"""One class's training on a single GPU inside a fixed wall-clock budget.

What a short time on a GPU machine is used for (docs/model.md gives the run that produced shipped weights):

1. generate the class's training split (``--objects`` objects, ``--seed``) and its test split
   (``--test-objects``, ``--test-seed``) with ``artdata generate`` on every CPU core;
2. train, at the same time on the one GPU, the dense estimator (continued from ``--init-from``)
   and the paper's full ResNet-18 MDN.  Each worker loads its data, times a few training steps
   on the GPU, and sets its number of epochs so that its training ends by its deadline;
3. the dense checkpoint is written without the inference fit (``fit=False``): run
   ``scripts/fit_dense_inference.py`` on the same split afterwards (any machine; the split is
   byte-reproducible from its seed);
4. the MDN predicts the test split and ``artdata score`` scores it (``mdn-score.json``).

Everything the run leaves is in ``--out``: ``dense-<class>.pt``, ``mdn-history.json``,
``mdn-score.json``, ``run.json`` (timings, epochs) and the workers' logs.

    python scripts/gpu_training_run.py --class cabinet --seed 27 --objects 10000 \\
        --init-from articulated_dataset/methods/weights/dense-cabinet.safetensors --minutes 9 --out run
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: Seconds the run keeps after the trainings for the MDN's test predictions and the files.
PREDICT_RESERVE_S = 100.0
#: Fraction of the measured step rate a worker plans with (the other worker shares the GPU and
#: the CPU cores; validation after every epoch).
RATE_SAFETY = 0.85
#: Training steps timed before a worker sets its epochs (the first few warm up the GPU).
PROBE_STEPS, PROBE_WARMUP = 25, 5
#: Seconds of CPU validation per dense epoch planned for.
DENSE_VALIDATION_S = 10.0

log = logging.getLogger("gpu_training_run")


def artdata(*args: str, log_file: Path) -> None:
    with open(log_file, "a") as f:
        subprocess.run([sys.executable, "-m", "articulated_dataset.cli", *args], check=True, stdout=f,
                       stderr=subprocess.STDOUT, cwd=REPO)


def epochs_for(seconds_left: float, steps_per_s: float, steps_per_epoch: int, per_epoch_s: float = 0.0) -> int:
    """Whole epochs that fit ``seconds_left`` at ``RATE_SAFETY`` of the measured rate (at least 1)."""
    epoch_s = steps_per_epoch / (steps_per_s * RATE_SAFETY) + per_epoch_s
    return max(1, int(seconds_left // epoch_s))


def sync(dev) -> None:
    import torch

    if dev.type == "cuda":
        torch.cuda.synchronize()


def dense_worker(a) -> None:
    import numpy as np
    import torch

    from articulated_dataset.methods.dense import train as dense_train
    from articulated_dataset.methods.dense.checkpoint import build_dense_model, load_dense_checkpoint
    from articulated_dataset.methods.dense.data import load_dense_split
    from articulated_dataset.methods.dense.features import make_inputs
    from articulated_dataset.methods.mdn.data import resolve_split_dir, split_by_object

    torch.set_num_threads(a.threads)
    split_dir = resolve_split_dir(a.data)
    init = load_dense_checkpoint(a.init_from)
    c = init["model_config"]
    t0 = time.time()
    data = load_dense_split(split_dir, c["n_joints"], (c["height_px"], c["width_px"]), max_objects=a.max_objects)
    load_s = time.time() - t0
    # the step rate, measured on a throwaway copy of the network
    dev = torch.device(a.device)
    model = build_dense_model(init).to(dev).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-6)
    q_scale = torch.tensor(init["q_scale"], dtype=torch.float32, device=dev)
    rng = np.random.default_rng(0)
    for i in range(PROBE_STEPS):
        if i == PROBE_WARMUP:
            sync(dev)
            t1 = time.time()
        idx = np.sort(rng.choice(len(data.depth_q), a.batch_size, replace=False))
        inputs = make_inputs(data.depth(idx).to(dev), torch.from_numpy(data.K[idx]).to(dev))
        loss, _ = dense_train.dense_loss(model, model(inputs["x"]), inputs, data, idx, q_scale, a.origin_weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
    sync(dev)
    rate = (PROBE_STEPS - PROBE_WARMUP) / (time.time() - t1)
    del model, opt
    steps_per_epoch = int(split_by_object(data.object_index, a.val_fraction, a.train_seed)[0].sum()) // a.batch_size
    epochs = epochs_for(a.deadline - time.time(), rate, steps_per_epoch, DENSE_VALIDATION_S)
    info = {"load_s": round(load_s, 1), "steps_per_s": round(rate, 2), "images_per_s": round(rate * a.batch_size),
            "epochs": epochs, "n_images": int(len(data.depth_q))}
    (Path(a.out) / "dense-run.json").write_text(json.dumps(info, indent=1))
    log.info("dense: %s", info)
    dense_train.load_dense_split = lambda *args, **kw: data  # the split is already in memory
    config = dense_train.DenseTrainConfig(class_name=a.class_name, epochs=epochs, batch_size=a.batch_size, lr=a.lr,
                                          width=c["width"], val_fraction=a.val_fraction, max_objects=a.max_objects,
                                          seed=a.train_seed, init_from=a.init_from, origin_weight=a.origin_weight)
    t2 = time.time()
    dense_train.train_dense(split_dir, Path(a.out) / f"dense-{a.class_name}.pt", config, progress=False,
                            device=a.device, fit=False)
    info["train_s"] = round(time.time() - t2, 1)
    (Path(a.out) / "dense-run.json").write_text(json.dumps(info, indent=1))


def mdn_worker(a) -> None:
    import torch

    from articulated_dataset.methods.mdn import train as mdn_train
    from articulated_dataset.methods.mdn.config import TrainConfig
    from articulated_dataset.methods.mdn.data import load_split, resolve_split_dir, split_by_object
    from articulated_dataset.methods.mdn.model import MixtureDensityNetwork
    from articulated_dataset.methods.mdn.preprocess import assemble_inputs
    from articulated_dataset.training.targets import TargetLayout

    torch.set_num_threads(a.threads)
    split_dir = resolve_split_dir(a.data)
    config = TrainConfig(class_name=a.class_name, preset="full", seed=a.train_seed).resolved()
    layout = TargetLayout.for_class(a.class_name)
    t0 = time.time()
    prepared = load_split(split_dir, layout, config.input_config(), max_objects=a.max_objects, workers=a.threads)
    load_s = time.time() - t0
    dev = torch.device(a.device)
    n_out = prepared.targets.shape[1]
    model = MixtureDensityNetwork(config.model_config(n_out)).to(dev, memory_format=torch.channels_last).train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-6)
    B = config.batch_size
    planes = prepared.planes[:B].to(dev)
    scalars = prepared.scalars[:B].to(dev)
    for i in range(PROBE_STEPS):
        if i == PROBE_WARMUP:
            sync(dev)
            t1 = time.time()
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=dev.type == "cuda"):
            out = model(assemble_inputs(planes, config.input_config()).contiguous(memory_format=torch.channels_last),
                        scalars)
            loss = sum(o.float().mean() for o in (out if isinstance(out, (tuple, list)) else [out]))
        opt.zero_grad()
        loss.backward()
        opt.step()
    sync(dev)
    rate = (PROBE_STEPS - PROBE_WARMUP) / (time.time() - t1)
    del model, opt, planes, scalars
    n_train = int(split_by_object(prepared.object_index, config.val_fraction, config.seed)[0].sum())
    epochs = epochs_for(a.deadline - time.time(), rate, n_train // B)
    info = {"load_s": round(load_s, 1), "steps_per_s": round(rate, 2), "images_per_s": round(rate * B),
            "epochs": epochs, "n_images": int(len(prepared.object_index))}
    log.info("mdn: %s", info)
    (Path(a.out) / "mdn-run.json").write_text(json.dumps(info, indent=1))
    mdn_train.load_split = lambda *args, **kw: prepared  # already in memory
    config = TrainConfig(class_name=a.class_name, preset="full", seed=a.train_seed, epochs=epochs,
                         max_objects=a.max_objects)
    t2 = time.time()
    ckpt = mdn_train.train(split_dir, Path(a.work) / "mdn.pt", config, device=a.device, progress=False)
    info["train_s"] = round(time.time() - t2, 1)
    info["history"] = ckpt.get("history")
    (Path(a.out) / "mdn-run.json").write_text(json.dumps(info, indent=1, default=str))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--class", dest="class_name", required=True)
    p.add_argument("--seed", type=int, required=True, help="training split's dataset seed")
    p.add_argument("--objects", type=int, default=10000)
    p.add_argument("--test-seed", type=int, default=2026)
    p.add_argument("--test-objects", type=int, default=1000)
    p.add_argument("--init-from", required=True, help="dense checkpoint to continue from")
    p.add_argument("--minutes", type=float, required=True, help="wall-clock budget of the whole run")
    p.add_argument("--dense-objects", type=int, default=None, help="train the dense model on the first N objects")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--origin-weight", type=float, default=3.0)
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--val-fraction", type=float, default=0.02)
    p.add_argument("--train-seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=os.cpu_count())
    p.add_argument("--no-mdn", action="store_true")
    p.add_argument("--device", default="cuda", help="cpu: a smoke test of the script")
    p.add_argument("--out", required=True)
    p.add_argument("--work", default="/tmp/gpu_training_run")
    p.add_argument("--role", choices=("main", "dense", "mdn"), default="main", help=argparse.SUPPRESS)
    p.add_argument("--deadline", type=float, default=None, help=argparse.SUPPRESS)
    p.add_argument("--data", default=None, help=argparse.SUPPRESS)
    p.add_argument("--max-objects", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--threads", type=int, default=4, help=argparse.SUPPRESS)
    a = p.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if a.role == "dense":
        return dense_worker(a)
    if a.role == "mdn":
        return mdn_worker(a)

    start = time.time()
    end = start + 60 * a.minutes
    out, work = Path(a.out), Path(a.work)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    run = {"argv": sys.argv, "class": a.class_name}
    gen_log = work / "generate.log"
    t = time.time()
    artdata("generate", "--class", a.class_name, "--n", str(a.objects), "--split", "train", "--seed", str(a.seed),
            "--out", str(work / "data"), "--workers", str(a.workers), "-q", log_file=gen_log)
    run["generate_train_s"] = round(time.time() - t, 1)
    log.info("train split: %s s", run["generate_train_s"])
    train_dir = work / "data" / a.class_name / "train"
    base = [sys.executable, __file__, "--class", a.class_name, "--seed", str(a.seed), "--init-from", a.init_from,
            "--minutes", "0", "--out", str(out), "--work", str(work), "--data", str(train_dir),
            "--lr", str(a.lr), "--origin-weight", str(a.origin_weight), "--batch-size", str(a.batch_size),
            "--val-fraction", str(a.val_fraction), "--train-seed", str(a.train_seed), "--device", a.device]
    procs = {}
    threads = max(1, (a.workers or 2) // 2)
    dense_args = ["--role", "dense", "--deadline", str(end - 20), "--threads", str(threads)]
    if a.dense_objects:
        dense_args += ["--max-objects", str(a.dense_objects)]
    procs["dense"] = subprocess.Popen(base + dense_args, stdout=open(out / "dense.log", "w"), stderr=subprocess.STDOUT)
    if not a.no_mdn:
        procs["mdn"] = subprocess.Popen(base + ["--role", "mdn", "--deadline", str(end - PREDICT_RESERVE_S),
                                                "--threads", str(threads)],
                                        stdout=open(out / "mdn.log", "w"), stderr=subprocess.STDOUT)
    rcs = {}
    if "mdn" in procs:
        t = time.time()
        artdata("generate", "--class", a.class_name, "--n", str(a.test_objects), "--split", "test", "--seed",
                str(a.test_seed), "--out", str(work / "data"), "--workers", "2", "-q", log_file=gen_log)
        run["generate_test_s"] = round(time.time() - t, 1)
        rcs["mdn"] = procs["mdn"].wait()
        if rcs["mdn"] == 0:
            t = time.time()
            artdata("predict", "--model", str(work / "mdn.pt"), str(work / "data" / a.class_name / "test"),
                    "--out", str(work / "mdn-test-predictions.h5"), "--device", a.device, "-q", log_file=out / "mdn.log")
            artdata("score", str(work / "mdn-test-predictions.h5"), "--truth", str(work / "data" / a.class_name / "test"),
                    "--json", str(out / "mdn-score.json"), log_file=out / "mdn.log")
            run["mdn_predict_s"] = round(time.time() - t, 1)
    rcs["dense"] = procs["dense"].wait()
    run["return_codes"] = rcs
    run["total_s"] = round(time.time() - start, 1)
    run["generate_log_tail"] = gen_log.read_text().splitlines()[-20:] if gen_log.exists() else []
    (out / "run.json").write_text(json.dumps(run, indent=1))
    log.info("done: %s", run)


if __name__ == "__main__":
    main()
