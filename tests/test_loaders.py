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

from articulated_dataset.errors import UserError
from articulated_dataset.loaders.reader import DEFAULT_FIELDS, ShardReader, plan_epoch
from articulated_dataset.schema import K_DATASET

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


def assert_batch_equals_raw(batch: dict, raw: dict, keys=None):
    idx = np.asarray(batch["index"])
    for k in keys or [k for k in batch if k in raw]:
        got = batch[k]
        if isinstance(got, list):  # torch: strings
            assert got == [raw[k][i].decode() for i in idx], k
            continue
        got = np.asarray(got)
        assert got.dtype == raw[k].dtype, k
        np.testing.assert_array_equal(got, raw[k][idx], err_msg=k)


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
        seen = []
        for p in range(parts):
            for b in plan_epoch(sizes, batch_size=batch, seed=3, epoch=epoch, part_index=p, part_count=parts,
                                block_size=block):
                assert 0 < len(b) <= batch
                seen.append(b)
        seen = np.concatenate(seen)
        np.testing.assert_array_equal(np.sort(seen), np.arange(n))


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
    parts = [plan_epoch(sizes, batch_size=3, part_index=p, part_count=3, block_size=2, equal_parts=True)
             for p in range(3)]
    lengths = {sum(len(b) for b in part) for part in parts}
    assert len(lengths) == 1
    dropped = plan_epoch(sizes, batch_size=5, drop_last=True)
    assert [len(b) for b in dropped] == [5, 5, 5]
    with pytest.raises(UserError, match="batch size"):
        plan_epoch(sizes, batch_size=0)
    with pytest.raises(UserError, match="part index"):
        plan_epoch(sizes, batch_size=2, part_index=2, part_count=2)
    with pytest.raises(UserError, match="seed"):
        plan_epoch(sizes, batch_size=2, seed=-1)


# --------------------------------------------------------------------------------------
# PyTorch

def test_torch_iterable_exactly_once_across_workers_and_ranks(cab, raw):
    pytest.importorskip("torch")
    from articulated_dataset.loaders.torch import make_loader

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
    from articulated_dataset.loaders.torch import DepthDataset, make_loader

    ds = DepthDataset(cab)
    item = ds[3]
    assert isinstance(item["depth"], torch.Tensor) and item["depth"].shape == raw["depth"].shape[1:]
    assert item["class"] == "cabinet" and int(item["index"]) == 3
    np.testing.assert_array_equal(item["mask"].numpy(), raw["mask"][3])
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


def test_torch_single_sample_iterable_and_spawn(cab, raw):
    torch = pytest.importorskip("torch")
    from articulated_dataset.loaders.torch import ShardIterableDataset

    ds = ShardIterableDataset(cab, ["depth", "q"], read_size=8, seed=2)
    loader = torch.utils.data.DataLoader(ds, batch_size=7, num_workers=1, multiprocessing_context="spawn")
    idx = np.concatenate([b["index"].numpy() for b in loader])
    np.testing.assert_array_equal(np.sort(idx), np.arange(len(raw["depth"])))
    first = next(iter(loader))
    np.testing.assert_array_equal(first["depth"].numpy(), raw["depth"][first["index"].numpy()])


def test_torch_targets_in_batches(cab, raw):
    pytest.importorskip("torch")
    from articulated_dataset.loaders.torch import make_loader
    from articulated_dataset.targets import NormStats, TargetLayout

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


# --------------------------------------------------------------------------------------
# JAX

def test_jax_loader_matches_torch_and_raw(cab, raw):
    pytest.importorskip("torch")
    pytest.importorskip("grain")
    from articulated_dataset.loaders.jax import JaxLoader
    from articulated_dataset.loaders.torch import DepthDataset, ShardIterableDataset
    from articulated_dataset.transforms import Compose, PixelDropout, RandomCrop

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
            for k in jb:
                np.testing.assert_array_equal(jb[k], tb[k].numpy(), err_msg=k)
            db = dd[jb["index"]]
            np.testing.assert_array_equal(db["depth"].numpy(), jb["depth"])
            assert_batch_equals_raw(jb, raw, keys=["q", "axis_pose", "sample_id"])  # labels: not transformed
        if epoch == 0:
            first = pairs[0][0]
    assert first["depth"].shape[1:] == (100, 180)
    assert not np.array_equal(first["index"], pairs[0][0]["index"])  # epoch 1 is shuffled differently


def test_jax_processes_cover_split_and_grain_workers(cab, raw):
    pytest.importorskip("grain")
    from articulated_dataset.loaders.jax import JaxLoader

    seen = []
    for p in range(3):
        for batch in JaxLoader(cab, 10, process_index=p, process_count=3, seed=1):
            assert "class" not in batch  # numeric fields only by default
            assert_batch_equals_raw(batch, raw)
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
    from articulated_dataset.loaders.jax import ShardDataSource

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
    code = ("import sys, articulated_dataset, articulated_dataset.loaders, articulated_dataset.targets, "
            "articulated_dataset.transforms, articulated_dataset.cli; "
            "bad = [m for m in ('torch', 'jax', 'grain') if m in sys.modules]; print(bad); sys.exit(bool(bad))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
