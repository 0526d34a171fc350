"""The package's one process pool (:func:`articulated_dataset.core.pool.process_map`): results in
order or as they finish, the initializer runs in every worker, and a worker that dies gives a
one-line error instead of a hang, in every user of the pool (generation's executor, verify,
and the NN and ICP baselines, which used ``multiprocessing.Pool`` before)."""

from __future__ import annotations

import itertools
import os
import signal
import time
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from articulated_dataset.core import pool as executors
from articulated_dataset.core.errors import UserError
from articulated_dataset.core.pool import WORKER_DIED, ProcessExecutor, process_map
from articulated_dataset.methods.baselines import icp, nn
from articulated_dataset.tools.verify import split as verify_split_module

#: Seconds a pool may take to report a dead worker (spawning workers on a loaded machine included).
DEADLINE_S = 120

_STATE = {"initialised": None}


def _initialise(value):
    _STATE["initialised"] = value


def _initialise_any(*args):
    """An initializer of any signature (ICP's also builds its model in the main process first)."""
    _STATE["initialised"] = args


def _slow_square(x):
    """Later tasks finish first, so unordered results come in another order than the tasks."""
    time.sleep(0.05 * (4 - x % 4))
    return x * x


def _with_state(x):
    return x, _STATE["initialised"], os.getpid()


def _die(*args, **kwargs):
    os._exit(3)


@contextmanager
def deadline(seconds: float = DEADLINE_S):
    """Fail (rather than hang) when the body runs longer than ``seconds``."""
    def expired(signum, frame):
        raise TimeoutError(f"still waiting after {seconds} s: the pool hangs")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.slow
def test_ordered_and_unordered_results():
    with deadline():
        ordered = list(process_map(_slow_square, range(8), 2, ordered=True))
        unordered = list(process_map(_slow_square, iter(range(8)), 2))
    assert ordered == [x * x for x in range(8)]
    assert sorted(unordered) == ordered


def test_the_initializer_runs_in_each_worker_not_here():
    with deadline():
        out = list(process_map(_with_state, range(6), 2, ordered=True, initializer=_initialise, initargs=("ready",)))
    assert [x for x, _, _ in out] == list(range(6))
    assert {state for _, state, _ in out} == {"ready"}
    assert os.getpid() not in {pid for _, _, pid in out} and _STATE["initialised"] is None


def test_an_endless_task_stream_is_consumed_lazily():
    with deadline():
        stream = process_map(_slow_square, itertools.count(), 2, ordered=True)
        first = list(itertools.islice(stream, 5))
        stream.close()  # shuts the pool down with the unfinished tasks cancelled
    assert first == [0, 1, 4, 9, 16]


def test_a_dead_worker_is_one_error_not_a_hang():
    with deadline(), pytest.raises(UserError) as info:
        list(process_map(_die, range(4), 2))
    assert str(info.value) == WORKER_DIED


def test_generation_executor_says_resume():
    with deadline(), pytest.raises(UserError, match="continue with resume"):
        list(ProcessExecutor(2).map_unordered(_die, range(4)))


def test_verify_workers(monkeypatch):
    monkeypatch.setattr(verify_split_module, "_check_shard_task", _die)
    with deadline(), pytest.raises(UserError, match="worker process died"):
        list(verify_split_module._map([1, 2, 3], 2, None))


def test_nn_feature_workers(monkeypatch, tmp_path):
    monkeypatch.setattr(nn, "_shard_features", _die)
    split = SimpleNamespace(shards=[SimpleNamespace(path=tmp_path / f"{i}.h5") for i in range(3)],
                            class_name="drawer", path=tmp_path / "train")
    with deadline(), pytest.raises(UserError, match="worker process died"):
        nn.split_features(split, workers=2)


class _FakeSplit:
    """What :func:`icp.predict` reads of its train, test and mean-object splits."""

    def __init__(self, path: Path, n_images: int):
        self.path, self.n_images, self.class_name, self.yaw_range_rad = path, n_images, "drawer", (0.0, 1.0)
        self.shards = [_FakeShard(path / "shard_0.h5", n_images)]

    def read(self, name):
        return np.arange(self.n_images)

    def close(self):
        pass


class _FakeShard:
    def __init__(self, path: Path, n: int):
        self.path, self.n = path, n

    def __len__(self):
        return self.n


def test_icp_workers(monkeypatch, tmp_path):
    monkeypatch.setattr(icp, "TASK_IMAGES", 1)  # one task per image: 3 tasks for 2 workers
    monkeypatch.setattr(icp, "ensure_mean_object", lambda train, mean, workers=1: tmp_path / "mean")
    monkeypatch.setattr(icp, "open_split_checked", lambda path, what: _FakeSplit(Path(path), 3))
    monkeypatch.setattr(icp, "check_compatible", lambda a, b: None)
    monkeypatch.setattr(icp, "_init_worker", _initialise_any)
    monkeypatch.setattr(icp, "_run_task", _die)
    with deadline(), pytest.raises(UserError, match="worker process died"):
        icp.predict(tmp_path / "train", tmp_path / "test", workers=2)


def test_the_deadline_fires():
    """The checks above can fail: a body that outlives its deadline raises."""
    with pytest.raises(TimeoutError):
        with deadline(0.2):
            time.sleep(5)


def test_workers_must_be_positive():
    with pytest.raises(ValueError):
        list(process_map(_slow_square, range(2), 0))
    assert executors.QUEUED_TASKS_PER_WORKER >= 1
