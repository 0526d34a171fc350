"""Reader, epoch plan, PyTorch and JAX loaders against raw HDF5 values.

Raw values are read here with plain h5py (``f[name][i]``), independently of the reader's
batched ``read_direct`` path.
"""

import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from articulated_dataset.core.errors import UserError
from articulated_dataset.format import K_DATASET
from articulated_dataset.training.loaders.epoch import plan_epoch
from articulated_dataset.training.loaders.reader import DEFAULT_FIELDS, ShardReader

SPLIT_KEYS = list(DEFAULT_FIELDS)


def raw_split(split_dir) -> dict:
    """Every field of every image of a split, in manifest order, via plain h5py."""
    manifest = json.loads((Path(split_dir) / "manifest.json").read_text())
    parts = []
    for rec in manifest["shards"]:
        with h5py.File(Path(split_dir) / rec["file"], "r") as f:
            n = f["depth"].shape[0]
            d = {k: f[k][()] for k in SPLIT_KEYS if k != "K"}
            d["K"] = np.repeat(f[K_DATASET][()][None], n, axis=0)
            parts.append(d)
    return {k: np.concatenate([p[k] for p in parts]) for k in SPLIT_KEYS}


@pytest.fixture(scope="module")
def cab(tiny_root):
    return tiny_root / "cabinet" / "train"


@pytest.fixture(scope="module")
def raw(cab):
    return raw_split(cab)


#: Where each framework's loader puts depth's channel axis: torch (B, 1, H, W), JAX (B, H, W, 1).
DEPTH_AXIS = {"torch": 1, "jax": 3}


def assert_batch_equals_raw(batch: dict, raw: dict, keys=None, framework="torch"):
    """Loader batch == raw HDF5 values, in the loaders' layout: depth with a channel axis, K float32."""
    idx = np.asarray(batch["index"])
    for k in keys or [k for k in batch if k in raw]:
        got = batch[k]
        if isinstance(got, list):  # torch: strings
            assert got == [raw[k][i].decode() for i in idx], k
            continue
        got, want = np.asarray(got), raw[k][idx]
        if k == "depth":
            want = np.expand_dims(want, DEPTH_AXIS[framework])
        if k == "K":
            want = want.astype(np.float32)
        assert got.dtype == want.dtype and got.shape == want.shape, (k, got.dtype, got.shape)
        np.testing.assert_array_equal(got, want, err_msg=k)


# --------------------------------------------------------------------------------------
# reader

def test_reader_items_equal_raw_hdf5(cab, raw):
    reader = ShardReader(cab)
    n = len(raw["depth"])
    assert len(reader) == n and reader.class_names == ["cabinet"]
    assert reader._state is None  # nothing opened before the first read
    sizes = reader.shard_sizes
    boundary = int(sizes[0])
    for i in (0, boundary - 1, boundary, n - 1, -1):
        item = reader[i]
        for k in SPLIT_KEYS:
            np.testing.assert_array_equal(item[k], raw[k][i % n], err_msg=f"{k}[{i}]")
    idx = np.array([boundary + 3, 2, 2, boundary - 1, boundary, 0, n - 1])  # unsorted, duplicate, across shards
    batch = reader.get_batch(idx)
    for k in SPLIT_KEYS:
        np.testing.assert_array_equal(batch[k], raw[k][idx], err_msg=k)
    assert reader.split_of(boundary) == cab and reader.class_of(0) == "cabinet"
    assert reader.get_batch([])["depth"].shape == (0,) + raw["depth"].shape[1:]
    with pytest.raises(IndexError):
        reader[n]
    with pytest.raises(IndexError, match=f"sample index {-n - 1} out of range"):  # the index given, not a shifted one
        reader[-n - 1]
    with pytest.raises(IndexError):
        reader.get_batch([0, n])


def test_reader_several_splits_and_classes(tiny_root, tmp_path):
    reader = ShardReader([tiny_root / "drawer" / "test", tiny_root / "cabinet2"], fields=["depth", "class_index", "class"])
    assert reader.class_names == ["drawer", "cabinet2"]
    assert [d.name for d in reader.split_dirs] == ["test", "test", "train"]  # find_split_dirs sorts
    n_drawer = len(ShardReader(tiny_root / "drawer" / "test"))
    batch = reader.get_batch([0, n_drawer, len(reader) - 1])
    np.testing.assert_array_equal(batch["class_index"], [0, 1, 1])
    assert list(batch["class"]) == [b"drawer", b"cabinet2", b"cabinet2"]
    assert reader.split_of(len(reader) - 1).name == "train"
    with pytest.raises(UserError, match="joint"):
        ShardReader([tiny_root / "drawer", tiny_root / "cabinet2"])  # J = 1 and 2 labels cannot stack
    with pytest.raises(UserError, match="unknown field"):
        ShardReader(tiny_root / "drawer", fields=["depth", "colour"])
    with pytest.raises(UserError, match="no generated split"):
        ShardReader(tmp_path)


def test_reader_reopens_per_process(cab, raw):
    reader = ShardReader(cab, fields=["depth", "q"])
    reader[0]  # opens files in this process
    clone = pickle.loads(pickle.dumps(reader))
    assert clone._state is None
    np.testing.assert_array_equal(clone[5]["depth"], raw["depth"][5])
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: must reopen (pid check), not reuse the parent's handles
        ok = np.array_equal(reader[7]["depth"], raw["depth"][7]) and reader._state.pid == os.getpid()
        os.write(w, b"1" if ok else b"0")
        os._exit(0)
    os.waitpid(pid, 0)
    assert os.read(r, 1) == b"1"
    assert reader._state.pid == os.getpid()
    np.testing.assert_array_equal(reader[7]["depth"], raw["depth"][7])


# --------------------------------------------------------------------------------------
# epoch plan

@pytest.mark.parametrize("sizes,parts,block,batch", [([64, 32], 1, 4, 16), ([64, 32], 3, 4, 10), ([7, 5, 9], 4, 3, 2),
                                                     ([10], 16, 4, 3), ([100, 1, 33], 6, 8, 7)])
def test_plan_covers_every_sample_once(sizes, parts, block, batch):
    n = sum(sizes)
    for epoch in (0, 1):
        by_mode = {}
        for remainder in ("pad", "drop", "uneven"):
            per_part = []
            for p in range(parts):
                plan = plan_epoch(sizes, batch_size=batch, seed=3, epoch=epoch, part_index=p, part_count=parts,
                                  block_size=block, remainder=remainder)
                assert all(0 < len(b) <= batch for b in plan)
                per_part.append(np.concatenate(plan) if plan else np.zeros(0, np.int64))
            by_mode[remainder] = per_part
            counts = [len(x) for x in per_part]
            if remainder != "uneven":  # equal parts: the same number of samples, hence batches
                assert len(set(counts)) == 1
                assert len({len(plan_epoch(sizes, batch_size=batch, seed=3, epoch=epoch, part_index=p,
                                           part_count=parts, block_size=block, remainder=remainder))
                            for p in range(parts)}) == 1
            else:
                assert max(counts) - min(counts) <= 1
        seen = np.concatenate(by_mode["uneven"])
        np.testing.assert_array_equal(np.sort(seen), np.arange(n))  # exactly once
        padded = np.concatenate(by_mode["pad"])  # every sample, plus the first ones again
        assert len(padded) == -(-n // parts) * parts
        np.testing.assert_array_equal(np.unique(padded), np.arange(n))
        dropped = np.concatenate(by_mode["drop"])  # no sample twice, n mod parts left out
        assert len(dropped) == len(np.unique(dropped)) == n // parts * parts


def test_plan_shuffling_is_deterministic_and_changes_per_epoch():
    sizes = [64, 64, 32]
    kw = dict(batch_size=16, part_index=1, part_count=2)
    a = np.concatenate(plan_epoch(sizes, seed=1, epoch=0, **kw))
    assert np.array_equal(a, np.concatenate(plan_epoch(sizes, seed=1, epoch=0, **kw)))
    assert not np.array_equal(a, np.concatenate(plan_epoch(sizes, seed=1, epoch=1, **kw)))
    assert not np.array_equal(a, np.concatenate(plan_epoch(sizes, seed=2, epoch=0, **kw)))
    ordered = np.concatenate(plan_epoch(sizes, batch_size=16, shuffle=False))
    np.testing.assert_array_equal(ordered, np.arange(160))
    blocks = plan_epoch(sizes, batch_size=4, block_size=4, seed=0)
    assert all(np.array_equal(b, np.arange(b[0], b[0] + 4)) for b in blocks)  # a block is contiguous
    assert not np.array_equal(np.concatenate(blocks), np.arange(160))


def test_plan_options():
    sizes = [10, 7]
    dropped = plan_epoch(sizes, batch_size=5, drop_last=True)
    assert [len(b) for b in dropped] == [5, 5, 5]
    with pytest.raises(UserError, match="batch size"):
        plan_epoch(sizes, batch_size=0)
    with pytest.raises(UserError, match="part index"):
        plan_epoch(sizes, batch_size=2, part_index=2, part_count=2)
    with pytest.raises(UserError, match="seed"):
        plan_epoch(sizes, batch_size=2, seed=-1)
    with pytest.raises(UserError, match="remainder"):
        plan_epoch(sizes, batch_size=2, remainder="equal")


# --------------------------------------------------------------------------------------
# PyTorch

def test_torch_iterable_exactly_once_across_workers_and_ranks(cab, raw):
    pytest.importorskip("torch")
    from articulated_dataset.training.loaders.torch import make_loader

    # persistent workers (make_loader's default) must see set_epoch through the shared epoch
    loaders = [make_loader(cab, batch_size=16, num_workers=2, rank=rank, world_size=2, seed=5) for rank in range(2)]
    orders = {}
    for epoch in (0, 1):
        seen = []
        for loader in loaders:
            loader.set_epoch(epoch)
            for batch in loader:
                assert_batch_equals_raw(batch, raw)
                seen.append(batch["index"].numpy())
        orders[epoch] = np.concatenate(seen)
        np.testing.assert_array_equal(np.sort(orders[epoch]), np.arange(len(raw["depth"])))
    assert not np.array_equal(orders[0], orders[1])
    fresh = make_loader(cab, batch_size=16, num_workers=2, rank=0, world_size=2, seed=5)
    fresh.set_epoch(1)
    first = {tuple(b["index"].tolist()) for b in fresh}
    assert first == {tuple(b["index"].tolist()) for b in loaders_epoch(loaders[0], 1)}


def loaders_epoch(loader, epoch):
    loader.set_epoch(epoch)
    return list(loader)


def test_torch_map_style_and_sampler(cab, raw):
    torch = pytest.importorskip("torch")
    from articulated_dataset.training.loaders.torch import DepthDataset, make_loader

    ds = DepthDataset(cab)
    item = ds[3]
    assert isinstance(item["depth"], torch.Tensor) and item["depth"].shape == (1,) + raw["depth"].shape[1:]
    assert item["mask"].shape == raw["mask"].shape[1:] and item["K"].dtype == torch.float32
    assert item["class"] == "cabinet" and int(item["index"]) == 3
    np.testing.assert_array_equal(item["mask"].numpy(), raw["mask"][3])
    n = len(ds)  # a batch's negative indices count from the end, as one sample's do
    assert int(ds[-1]["index"]) == n - 1
    np.testing.assert_array_equal(ds[[0, -1, 3]]["index"].numpy(), [0, n - 1, 3])
    with pytest.raises(IndexError):
        ds[[0, -n - 1]]
    # default DataLoader auto-batching goes through __getitems__
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=5)))
    np.testing.assert_array_equal(batch["index"].numpy(), np.arange(5))
    assert_batch_equals_raw(batch, raw)
    runs = []
    for _ in range(2):
        loader = make_loader(cab, batch_size=16, num_workers=2, iterable=False, seed=9)
        loader.set_epoch(1)
        runs.append(np.concatenate([b["index"].numpy() for b in loader]))
    np.testing.assert_array_equal(runs[0], runs[1])  # same seed and epoch: same order
    np.testing.assert_array_equal(np.sort(runs[0]), np.arange(len(raw["depth"])))


@pytest.mark.slow
def test_torch_single_sample_iterable_and_spawn(cab, raw):
    torch = pytest.importorskip("torch")
    from articulated_dataset.training.loaders.torch import ShardIterableDataset

    ds = ShardIterableDataset(cab, ["depth", "q"], read_size=8, seed=2)
    loader = torch.utils.data.DataLoader(ds, batch_size=7, num_workers=1, multiprocessing_context="spawn")
    idx = np.concatenate([b["index"].numpy() for b in loader])
    np.testing.assert_array_equal(np.sort(idx), np.arange(len(raw["depth"])))
    first = next(iter(loader))
    np.testing.assert_array_equal(first["depth"].numpy()[:, 0], raw["depth"][first["index"].numpy()])


def test_torch_targets_in_batches(cab, raw):
    pytest.importorskip("torch")
    from articulated_dataset.training.loaders.torch import make_loader
    from articulated_dataset.training.targets import NormStats, TargetLayout

    layout = TargetLayout.for_class("cabinet")
    stats = NormStats.from_split(cab, layout)
    loader = make_loader(cab, batch_size=32, num_workers=0, target=layout, norm=stats,
                         fields=["depth", "axis_pose", "q", "part_offset", "geometry"])
    for batch in loader:
        idx = batch["index"].numpy()
        want = stats.normalize(layout.encode({k: raw[k][idx] for k in layout.fields}))
        np.testing.assert_array_equal(batch["target"].numpy(), want)
    with pytest.raises(UserError, match="axis_pose"):
        make_loader(cab, fields=["depth", "q"], target=layout)


# PyTorch idioms (before any test imports jax: these fork DataLoader workers, and JAX is
# multithreaded): batches independent of workers, len, the stock DataLoader recipe

def test_batches_and_len_do_not_depend_on_num_workers(cab, raw):
    pytest.importorskip("torch")
    from articulated_dataset.training.loaders.torch import make_loader

    n = len(raw["depth"])  # 96: batches of 40 are [40, 40, 16]
    for iterable in (True, False):
        runs = {}
        for workers in (0, 1, 2):
            loader = make_loader(cab, batch_size=40, num_workers=workers, iterable=iterable, seed=3,
                                 fields=["depth", "q"], persistent_workers=False)
            batches = [b["index"].numpy() for b in loader]
            assert len(loader) == len(batches) == 3, (iterable, workers)
            runs[workers] = batches
        assert [len(b) for b in runs[0]] == [40, 40, n - 80]
        for workers in (1, 2):
            assert all(np.array_equal(a, b) for a, b in zip(runs[0], runs[workers], strict=True)), (iterable, workers)
    # the docs' quick start: one batch per epoch when the batch holds the whole split
    assert [len(b["index"]) for b in make_loader(cab, batch_size=128, num_workers=2, fields=["q"])] == [n]


def test_stock_dataloader_with_distributed_sampler_three_ranks(cab, raw):
    """The PyTorch recipe: DataLoader(DepthDataset, sampler=DistributedSampler) per rank and only
    ``sampler.set_epoch``: equal steps, every sample once per epoch, a new augmentation each epoch."""
    torch = pytest.importorskip("torch")
    from torch.utils.data import DataLoader, DistributedSampler

    from articulated_dataset.training.loaders.torch import DepthDataset
    from articulated_dataset.training.transforms import PixelDropout

    torch.manual_seed(0)
    n, world = len(raw["depth"]), 3
    ranks = []
    for rank in range(world):
        ds = DepthDataset(cab, ["depth", "q", "K"], transform=PixelDropout(0.5), seed=1)
        sampler = DistributedSampler(ds, num_replicas=world, rank=rank, shuffle=True, seed=7)
        workers = {0: dict(num_workers=2), 1: dict(num_workers=0),
                   2: dict(num_workers=1, persistent_workers=True)}[rank]
        ranks.append((sampler, DataLoader(ds, batch_size=5, sampler=sampler, **workers)))
    depth_by_epoch = []
    for epoch in range(2):
        depth, steps = {}, []
        for sampler, loader in ranks:
            sampler.set_epoch(epoch)
            batches = list(loader)
            steps.append(len(batches))
            assert len(loader) == len(batches)
            for b in batches:
                assert b["depth"].shape[1] == 1 and b["K"].dtype == torch.float32
                for i, d in zip(b["index"].tolist(), b["depth"][:, 0].numpy()):
                    assert i not in depth  # exactly once across ranks
                    depth[i] = d
                    kept = d > 0
                    np.testing.assert_array_equal(d[kept], raw["depth"][i][kept])  # dropout only
        assert len(set(steps)) == 1 and sorted(depth) == list(range(n))
        depth_by_epoch.append(depth)
    changed = [not np.array_equal(depth_by_epoch[0][i], depth_by_epoch[1][i]) for i in range(n)]
    assert all(changed), f"{changed.count(False)} of {n} samples kept their epoch-0 augmentation"


def test_three_ranks_get_equal_steps_by_default(tmp_path):
    """world_size=3 with the defaults (remainder="pad") on 2 objects x 16 images (32 = 3 x 10 + 2):
    every rank the same number of batches, len(loader) each rank's batches per epoch, every image seen."""
    pytest.importorskip("torch")
    from articulated_dataset.generation import GenerationConfig, generate_split
    from articulated_dataset.training.loaders.torch import make_loader

    split = generate_split(GenerationConfig("drawer", split="test", n_objects=2), tmp_path)
    for iterable in (True, False):
        steps, seen = [], []
        for rank in range(3):
            loader = make_loader(split, batch_size=5, num_workers=0, rank=rank, world_size=3, fields=["q"],
                                 iterable=iterable)
            idx = [b["index"].numpy() for b in loader]
            assert len(loader) == len(idx), (iterable, rank)
            steps.append(len(idx))
            seen.append(np.concatenate(idx))
        assert steps == [3, 3, 3], (iterable, steps)  # 11 samples a rank (one padded): 5, 5, 1; uneven: 3, 3, 2
        np.testing.assert_array_equal(np.unique(np.concatenate(seen)), np.arange(32))


# --------------------------------------------------------------------------------------
# JAX

@pytest.mark.slow
def test_jax_loader_matches_torch_and_raw(cab, raw):
    pytest.importorskip("torch")
    pytest.importorskip("grain")
    from articulated_dataset.training.loaders.jax import JaxLoader
    from articulated_dataset.training.loaders.torch import DepthDataset, ShardIterableDataset
    from articulated_dataset.training.transforms import Compose, PixelDropout, RandomCrop

    t = Compose([RandomCrop(100, 180), PixelDropout(0.1)])
    kw = dict(shuffle=True, seed=4, transform=t)
    jl = JaxLoader(cab, 16, process_index=1, process_count=2, **kw)
    tl = ShardIterableDataset(cab, jl.reader.fields, batch_size=16, rank=1, world_size=2, **kw)
    dd = DepthDataset(cab, jl.reader.fields, seed=4, transform=t)
    for epoch in (0, 1):
        jl.set_epoch(epoch)
        tl.set_epoch(epoch)
        dd.set_epoch(epoch)
        pairs = list(zip(jl, tl, strict=True))
        assert len(pairs) == len(jl) > 0
        for jb, tb in pairs:
            assert set(jb) == set(tb)
            assert all(isinstance(v, np.ndarray) for v in jb.values())
            assert jb["depth"].shape[3] == 1 and tb["depth"].shape[1] == 1  # channels-last / -first
            for k in jb:
                want = tb[k].numpy()[:, 0] if k == "depth" else tb[k].numpy()
                np.testing.assert_array_equal(jb[k][..., 0] if k == "depth" else jb[k], want, err_msg=k)
            db = dd[jb["index"]]
            np.testing.assert_array_equal(db["depth"].numpy()[:, 0], jb["depth"][..., 0])
            assert_batch_equals_raw(jb, raw, keys=["q", "axis_pose", "sample_id"])  # labels: not transformed
        if epoch == 0:
            first = pairs[0][0]
    assert first["depth"].shape[1:] == (100, 180, 1)
    assert not np.array_equal(first["index"], pairs[0][0]["index"])  # epoch 1 is shuffled differently


@pytest.mark.slow
def test_jax_processes_cover_split_and_grain_workers(cab, raw):
    pytest.importorskip("grain")
    from articulated_dataset.training.loaders.jax import JaxLoader

    seen = []
    for p in range(3):
        for batch in JaxLoader(cab, 10, process_index=p, process_count=3, seed=1):
            assert "class" not in batch  # numeric fields only by default
            assert_batch_equals_raw(batch, raw, framework="jax")
            seen.append(batch["index"])
    np.testing.assert_array_equal(np.sort(np.concatenate(seen)), np.arange(len(raw["depth"])))
    # grain worker processes (spawned, kept across epochs) give the in-process batches
    with JaxLoader(cab, 32, fields=["depth", "q"], num_workers=2, seed=1) as par:
        ref = JaxLoader(cab, 32, fields=["depth", "q"], num_workers=0, seed=1)
        for epoch in (0, 1):
            par.set_epoch(epoch)
            ref.set_epoch(epoch)
            for a, b in zip(par, ref, strict=True):
                for k in b:
                    np.testing.assert_array_equal(a[k], b[k])


def test_grain_data_source_protocol(cab, raw):
    grain = pytest.importorskip("grain")
    from articulated_dataset.training.loaders.jax import ShardDataSource

    src = ShardDataSource(cab, fields=["depth", "q", "sample_id"])
    assert isinstance(src, grain.sources.RandomAccessDataSource)
    assert "ShardDataSource" in repr(src) and len(src) == len(raw["depth"])
    batch = next(iter(grain.MapDataset.source(src).batch(8)))
    np.testing.assert_array_equal(batch["depth"], raw["depth"][:8])
    items = src._getitems([9, 3])
    np.testing.assert_array_equal(items[0]["q"], raw["q"][9])
    np.testing.assert_array_equal(items[1]["sample_id"], raw["sample_id"][3])


# --------------------------------------------------------------------------------------

def test_core_package_imports_neither_torch_nor_jax():
    code = ("import sys, articulated_dataset, articulated_dataset.training.loaders, articulated_dataset.training.targets, "
            "articulated_dataset.training.transforms, articulated_dataset.cli; "
            "bad = [m for m in ('torch', 'jax', 'grain') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


# --------------------------------------------------------------------------------------
# Equal steps, epochs without set_epoch, exact ids, missing optional dependencies

def test_equal_steps_per_rank_by_default(cab, raw):
    pytest.importorskip("torch")
    from articulated_dataset.training.loaders.jax import JaxLoader
    from articulated_dataset.training.loaders.torch import make_loader

    n, world = len(raw["depth"]), 5  # 96 = 5 x 19 + 1
    for remainder, per_rank in (("pad", 20), ("drop", 19)):
        steps, seen = set(), []
        for rank in range(world):
            for loader in (make_loader(cab, batch_size=4, num_workers=0, rank=rank, world_size=world, fields=["q"],
                                       remainder=remainder, iterable=rank % 2 == 0),
                           JaxLoader(cab, 4, fields=["q"], process_index=rank, process_count=world,
                                     remainder=remainder)):
                idx = [np.asarray(b["index"]) for b in loader]
                assert len(loader) == len(idx) and sum(map(len, idx)) == per_rank
                steps.add(len(idx))
            seen.append(np.concatenate(idx))
        assert steps == {5}
        seen = np.concatenate(seen)
        if remainder == "pad":
            np.testing.assert_array_equal(np.unique(seen), np.arange(n))
        else:
            assert len(np.unique(seen)) == len(seen) == n - 1
    sizes = [len(make_loader(cab, batch_size=4, num_workers=0, rank=r, world_size=world, remainder="uneven",
                             fields=["q"])) for r in range(world)]
    assert sum(sizes) == sum(-(-c // 4) for c in (19, 19, 19, 19, 20))


def test_loader_advances_the_epoch_without_set_epoch(cab):
    pytest.importorskip("torch")
    from articulated_dataset.training.loaders.jax import JaxLoader
    from articulated_dataset.training.loaders.torch import make_loader

    for make in (lambda: make_loader(cab, batch_size=32, num_workers=0, fields=["q"]),
                 lambda: JaxLoader(cab, 32, fields=["q"])):
        loader = make()
        passes = [np.concatenate([np.asarray(b["index"]) for b in loader]) for _ in range(2)]
        ref = make()
        ref.set_epoch(1)
        np.testing.assert_array_equal(passes[1], np.concatenate([np.asarray(b["index"]) for b in ref]))
        assert not np.array_equal(passes[0], passes[1])


@pytest.mark.slow
def test_grain_workers_keep_little_shared_memory(cab):
    """grain workers prepare only a few batches ahead, and close() leaves none of their shared-memory
    blocks behind (grain's default read-ahead held ~1000 batch blocks, left in /dev/shm at close)."""
    pytest.importorskip("grain")
    import time

    from articulated_dataset.training.loaders.jax import JaxLoader

    shm = Path("/dev/shm")
    if not shm.is_dir():
        pytest.skip("no /dev/shm to count shared-memory blocks in")
    batch = 7
    depth_bytes = batch * 108 * 192 * 4

    def blocks() -> set[str]:  # this loader's batch blocks: depth plus the few label bytes after it
        out = set()
        for p in shm.iterdir():
            try:
                if depth_bytes <= p.stat().st_size < depth_bytes + 4096:
                    out.add(p.name)
            except OSError:  # removed meanwhile
                pass
        return out

    before = blocks()
    loader = JaxLoader(cab, batch, fields=["depth", "q"], num_workers=2, seed=1)
    it = iter(loader)
    next(it)
    time.sleep(2.0)  # the workers read ahead as far as they will
    ahead = len(blocks() - before)
    assert ahead <= 40, f"{ahead} batch blocks in shared memory with 2 workers"
    del it
    loader.close()
    for _ in range(50):
        if len(blocks() - before) <= 2:
            break
        time.sleep(0.1)
    assert len(blocks() - before) <= 2, f"{len(blocks() - before)} batch blocks left in /dev/shm after close"


def test_jax_device_put_keeps_sample_ids_exact(cab, raw):
    pytest.importorskip("jax")
    from articulated_dataset.training.loaders.jax import JaxLoader, device_put

    batch = next(iter(JaxLoader(cab, 8, fields=["depth", "sample_id", "K"], shuffle=False)))
    big = np.array([3971172795307752716], dtype=np.int64)  # the value JAX turned into -33325812
    put = device_put({**batch, "sample_id": np.concatenate([batch["sample_id"][:-1], big])})
    assert put["sample_id"].dtype == np.int64 and int(put["sample_id"][-1]) == int(big[0])
    np.testing.assert_array_equal(put["sample_id"][:-1], raw["sample_id"][:7])
    assert put["depth"].shape == (8, 108, 192, 1) and str(put["K"].dtype) == "float32"


@pytest.mark.parametrize("block,code", [
    ("torch", "import articulated_dataset.training.loaders.torch"),
    ("grain", "from articulated_dataset.training.loaders.jax import JaxLoader; JaxLoader({cab!r}, 8, num_workers=2)"),
])
def test_missing_optional_dependency_is_one_line(cab, block, code):
    script = f"import sys; sys.modules[{block!r}] = None\n" + code.format(cab=str(cab))
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert res.returncode == 1
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith("ModuleNotFoundError: ") and f"needs {block}, which is not installed: pip install" in last
    assert "During handling" not in res.stderr  # one error, not a chain


def test_loaders_refuse_non_integer_batch_sizes_and_indices(split_copy):
    pytest.importorskip("torch")
    from articulated_dataset.training.loaders.torch import DepthDataset, make_loader

    split = split_copy()
    for bad in (0, 1.5, True):
        with pytest.raises(UserError, match="batch size"):
            make_loader(split, batch_size=bad)  # 0 would give one batch of every image
    ds = DepthDataset(split)
    for bad in ([0.4, 1.9], 1.5, "1"):
        with pytest.raises((TypeError, UserError)):
            ds[bad]  # [0.4, 1.9] must not read samples 0 and 1
    assert len(ds[[0, 1]]["depth"]) == 2
