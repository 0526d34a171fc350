"""Loader throughput: PyTorch DataLoader and JAX loader beside the raw h5py read rate.

All modes read the same shards in one run (one class, ``--objects`` objects x 16 images; the
data are generated into a temporary folder unless ``--data`` names a split folder):

* raw h5py, 1 process / N processes: ``f['depth'][a:b]``, ``f['mask'][a:b]`` and every label
  dataset in slabs of the batch size, shards split across processes: the floor of any loader
  (gzip decompression dominates).
* ShardReader: batches of the shuffled epoch plan (``plan_epoch``), one process.
* torch DataLoader, iterable (``make_loader``) and map-style (``iterable=False``), N workers.
* JAX loader in-process and with N grain worker processes.

Every loader returns every stored field plus ``K``, ``index`` and the normalised target vector.
For each mode, over epochs 2..E (epoch 1 warms the page cache and starts the workers; its wall
time is printed apart): samples/s, and CPU time per sample of this process and all its workers
(read from /proc), which does not depend on what else the machine runs.  ``est. idle`` =
``min(processes, 2) / CPU per sample``: the rate with a free core for each process, up to two.

    python benchmarks/loader_throughput.py                  # 200 cabinets, batch 128, 2 workers
    python benchmarks/loader_throughput.py --data OUT/cabinet/train --epochs 4

Target: >= 5,000 samples/s through the torch and JAX loaders on 2 cores, and >= 5,500 samples/s
through torch with 2 workers.
"""

from __future__ import annotations

import argparse
import gc
import os
import resource
import tempfile
import time
from pathlib import Path

TARGET_SAMPLES_PER_S = 5500
CORES = 2  # the target's machine


def _proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a live process (Linux /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def _live_descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*/children"):
            try:
                kids = [int(x) for x in task.read_text().split()]
            except OSError:
                continue
            out += kids
            todo += kids
    return out


def _cpu_s() -> float:
    """CPU seconds of this process, of its finished children and of its live descendants (worker
    processes), so a reading can be taken while persistent workers are running."""
    me = resource.getrusage(resource.RUSAGE_SELF)
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    live = sum(_proc_cpu_s(p) for p in _live_descendants(os.getpid()))
    return me.ru_utime + me.ru_stime + ch.ru_utime + ch.ru_stime + live


def _raw_read(args) -> int:
    """Read whole shards in slabs with plain h5py; returns the number of images."""
    paths, batch = args
    import h5py

    n = 0
    for p in paths:
        with h5py.File(p, "r") as f:
            names = [k for k in f.keys() if f[k].ndim >= 1 and f[k].shape[0] == f["depth"].shape[0]]
            N = f["depth"].shape[0]
            for a in range(0, N, batch):
                for k in names:
                    f[k][a : a + batch]
            n += N
    return n


def raw_h5py(paths: list[Path], batch: int, processes: int):
    def run():
        if processes == 1:
            return _raw_read((paths, batch))
        import multiprocessing as mp

        groups = [paths[i::processes] for i in range(processes)]
        with mp.get_context("fork").Pool(processes) as pool:
            return sum(pool.map(_raw_read, [(g, batch) for g in groups]))

    return run


def measure(name: str, epoch_fn, epochs: int, processes: int, make=None) -> dict:
    """Run ``epoch_fn(epoch[, loader])`` (returns images read) ``epochs`` times.

    Epoch 1 is the warm-up (page cache, worker start-up); rate and CPU time are taken over the
    following epochs.  ``make()`` builds the loader first; afterwards it is closed and dropped.
    """
    t0 = time.perf_counter()
    loader = make() if make is not None else None
    walls, counts, cpus = [], [], []
    for e in range(epochs):
        t = time.perf_counter()
        counts.append(epoch_fn(e) if loader is None else epoch_fn(e, loader))
        walls.append(time.perf_counter() - t)
        cpus.append(_cpu_s())
    first_s = walls[0] + (time.perf_counter() - t0 - sum(walls))
    if loader is not None:
        if hasattr(loader, "close"):
            loader.close()
        del loader
        gc.collect()
    steady = slice(1, None) if epochs > 1 else slice(0, None)
    n = sum(counts[steady])
    cpu = cpus[-1] - (cpus[0] if epochs > 1 else 0.0)
    return {"mode": name, "samples_per_s": n / sum(walls[steady]), "cpu_s_per_sample": cpu / n,
            "processes": processes, "first_epoch_s": first_s}


def _consume(epoch: int, loader) -> int:
    loader.set_epoch(epoch)
    n = 0
    for batch in loader:
        n += len(batch["index"])
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="a generated split folder (default: generate one)")
    ap.add_argument("--class", dest="class_name", default="cabinet")
    ap.add_argument("--objects", type=int, default=200)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--skip", default="", help="comma-separated modes to skip: raw,reader,torch,torch-map,jax,jax-workers")
    args = ap.parse_args()
    skip = set(filter(None, args.skip.split(",")))

    from articulated_dataset.training.loaders.batch import BatchProcessor, load_batch
    from articulated_dataset.training.loaders.epoch import plan_epoch
    from articulated_dataset.training.loaders.reader import ShardReader
    from articulated_dataset.training.targets import NormStats, TargetLayout

    tmp = None
    split = args.data
    if split is None:
        from articulated_dataset.generation import GenerationConfig, generate_split

        tmp = tempfile.TemporaryDirectory(prefix="loader-bench-")
        t = time.perf_counter()
        split = generate_split(GenerationConfig(args.class_name, split="train", n_objects=args.objects), tmp.name,
                               workers=args.workers)
        print(f"generated {split} in {time.perf_counter() - t:.1f} s")
    reader = ShardReader(split)
    layout = TargetLayout.for_class(reader.class_names[0])
    norm = NormStats.from_split(split, layout)
    H, W = reader.image_shape
    print(f"data: {split}: {len(reader)} images of {', '.join(reader.class_names)} ({W}x{H}) in "
          f"{len(reader.shard_paths)} shards; batch {args.batch}; {args.workers} workers; {args.epochs} epochs; "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")
    results = []
    if "raw" not in skip:
        for p in sorted({1, args.workers}):
            results.append(measure(f"raw h5py slabs, {p} process(es)",
                                   lambda e, p=p: raw_h5py(reader.shard_paths, args.batch, p)(), args.epochs, p))
    if "reader" not in skip:
        proc = BatchProcessor(reader.fields, target=layout, norm=norm)

        def reader_epoch(e):
            plan = plan_epoch(reader.shard_sizes, batch_size=args.batch, seed=0, epoch=e)
            return sum(len(load_batch(reader, proc, b, e)["index"]) for b in plan)

        results.append(measure("ShardReader, shuffled plan, 1 process", reader_epoch, args.epochs, 1))
    if "torch" not in skip or "torch-map" not in skip:
        from articulated_dataset.training.loaders.torch import make_loader

        for iterable, key in ((True, "torch"), (False, "torch-map")):
            if key in skip:
                continue
            label = "iterable" if iterable else "map-style"
            results.append(measure(
                f"torch DataLoader {label}, {args.workers} workers", _consume, args.epochs, args.workers,
                make=lambda it=iterable: make_loader(split, batch_size=args.batch, num_workers=args.workers,
                                                     target=layout, norm=norm, iterable=it)))
    if "jax" not in skip or "jax-workers" not in skip:
        from articulated_dataset.training.loaders.jax import JaxLoader

        for nw, key in ((0, "jax"), (args.workers, "jax-workers")):
            if key in skip:
                continue
            label = "in-process" if nw == 0 else f"{nw} grain workers"
            results.append(measure(f"JAX loader, {label}", _consume, args.epochs, max(nw, 1),
                                   make=lambda nw=nw: JaxLoader(split, args.batch, target=layout, norm=norm,
                                                                num_workers=nw)))
    print(f"\n{'mode':42s} {'samples/s':>10s} {'CPU us/sample':>14s} {'est. idle':>13s} {'epoch 1 s':>10s}")
    for r in results:
        est = min(r["processes"], CORES) / r["cpu_s_per_sample"]
        print(f"{r['mode']:42s} {r['samples_per_s']:10.0f} {1e6 * r['cpu_s_per_sample']:14.0f} {est:13.0f} "
              f"{r['first_epoch_s']:10.1f}")
    print(f"\ntarget: >= {TARGET_SAMPLES_PER_S} samples/s on {CORES} cores (load average now {os.getloadavg()[0]:.1f})")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
