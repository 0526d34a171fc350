"""Interrupting ``artdata generate`` (SIGKILL at random moments) and resuming gives the same
bytes as an uninterrupted run; existing output is refused without --resume."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner

from articulated_dataset.cli import main
from articulated_dataset.format import MANIFEST_NAME, sha256_file

#: Small but multi-shard: N_SHARDS objects, one per shard, 8 images each.
N_SHARDS = 10
ARGS = ["--class", "toaster", "--n", str(N_SHARDS), "--objects-per-shard", "1", "--images", "8", "--split", "train"]
#: Seed of the kill points.  A kill point is "once k shard files are visible, wait a further
#: uniform delay", k uniform in [0, N_SHARDS) and the delay in [0, MAX_EXTRA_DELAY_S), so
#: kills land at varied stages (start-up, mid-shard, between rename and manifest update...)
#: whatever the machine's speed.
KILL_SEED = 3  # kill points k = 8, 0, 1, 2 shards (the pool trial at 2)
N_TRIALS = 4
MAX_EXTRA_DELAY_S = 0.25
POLL_S = 0.005


def generate(out, *extra, workers=1):
    """Start ``artdata generate`` in its own process group (so SIGKILL reaches its workers)."""
    cmd = [sys.executable, "-m", "articulated_dataset.cli", "generate", *ARGS, "--out", str(out), "--quiet",
           "--workers", str(workers), *extra]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)


def files_of(split_dir):
    return {p.name: sha256_file(p) for p in sorted(split_dir.glob("shard-*.h5"))}


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    t0 = time.perf_counter()
    proc = generate(out)
    _, err = proc.communicate(timeout=120)
    seconds = time.perf_counter() - t0
    assert proc.returncode == 0, err.decode()
    split = out / "toaster" / "train"
    return {"seconds": seconds, "manifest": (split / MANIFEST_NAME).read_bytes(), "files": files_of(split)}


def _kill_and_resume(tmp_path, reference, k_shards, extra_delay_s, workers):
    out = tmp_path / f"run-{k_shards}-{extra_delay_s:.3f}-{workers}"
    proc = generate(out, workers=workers)
    split_dir = out / "toaster" / "train"
    while proc.poll() is None and len(list(split_dir.glob("shard-*.h5"))) < k_shards:
        time.sleep(POLL_S)
    time.sleep(extra_delay_s)
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    split = out / "toaster" / "train"
    # Whatever the moment of the kill: visible shards are complete and correct ...
    killed_with = files_of(split) if split.exists() else {}
    for name, digest in killed_with.items():
        assert digest == reference["files"][name], f"partial shard {name} became visible"
    # ... and the manifest is whole JSON listing only correct shards.
    if (split / MANIFEST_NAME).exists():
        m = json.loads((split / MANIFEST_NAME).read_text())
        for rec in m["shards"]:
            assert rec["sha256"] == reference["files"][rec["file"]]
    resumed = generate(out, "--resume", workers=workers)
    _, err = resumed.communicate(timeout=120)
    assert resumed.returncode == 0, err.decode()
    assert (split / MANIFEST_NAME).read_bytes() == reference["manifest"]
    assert files_of(split) == reference["files"]
    assert not list(split.glob("*.partial"))
    return len(killed_with)


@pytest.mark.slow
def test_kill_at_random_points_then_resume(tmp_path, reference):
    rng = np.random.default_rng(KILL_SEED)
    ks = rng.integers(0, N_SHARDS, size=N_TRIALS)
    delays = rng.uniform(0.0, MAX_EXTRA_DELAY_S, size=N_TRIALS)
    visible = []
    for t, (k, delay) in enumerate(zip(ks, delays)):
        # the last trial runs the process pool (killed as a group, as a terminal's kill would)
        visible.append(_kill_and_resume(tmp_path, reference, int(k), float(delay), workers=2 if t == N_TRIALS - 1 else 1))
    assert any(0 < v < N_SHARDS for v in visible), visible  # at least one kill landed mid-run


def test_existing_output_needs_resume_or_overwrite(tmp_path):
    runner = CliRunner()
    base = ["generate", "--class", "drawer", "--n", "2", "--images", "4", "--objects-per-shard", "1",
            "--workers", "1", "--quiet", "--out", str(tmp_path)]
    assert runner.invoke(main, base).exit_code == 0
    first = (tmp_path / "drawer" / "train" / MANIFEST_NAME).read_bytes()
    refused = runner.invoke(main, base)
    assert refused.exit_code == 2
    assert "--resume" in refused.output and "--overwrite" in refused.output
    assert len(refused.output.strip().splitlines()) == 1
    # other splits and other classes under the same --out are independent
    assert runner.invoke(main, [*base, "--split", "test"]).exit_code == 0
    assert runner.invoke(main, [*base[:2], "cabinet", *base[3:]]).exit_code == 0
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.glob("*/*/manifest.json")) == [
        "cabinet/train/manifest.json", "drawer/test/manifest.json", "drawer/train/manifest.json"]
    # resuming a complete run changes nothing; overwriting regenerates the same bytes
    assert runner.invoke(main, [*base, "--resume"]).exit_code == 0
    assert (tmp_path / "drawer" / "train" / MANIFEST_NAME).read_bytes() == first
    assert runner.invoke(main, [*base, "--overwrite"]).exit_code == 0
    assert (tmp_path / "drawer" / "train" / MANIFEST_NAME).read_bytes() == first
    # resuming with different settings is refused
    changed = runner.invoke(main, [*base, "--resume", "--seed", "7"])
    assert changed.exit_code == 2 and "different settings" in changed.output


@pytest.mark.slow
def test_killing_only_the_parent_ends_its_workers_and_resume_is_identical(tmp_path, reference):
    """SIGKILL of the generate process alone (not its group): its workers end with it
    instead of writing on and hanging, and --resume still gives the reference bytes."""
    psutil = pytest.importorskip("psutil")
    out = tmp_path / "orphans"
    split = out / "toaster" / "train"
    proc = generate(out, workers=2)
    workers = []
    while proc.poll() is None and not (workers and list(split.glob("shard-*.h5"))):
        workers = [c for c in psutil.Process(proc.pid).children(recursive=True) if c.is_running()]
        time.sleep(POLL_S)
    assert proc.poll() is None, "the run ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    _, alive = psutil.wait_procs(workers, timeout=10)
    assert not alive, f"workers outlived their parent: {alive}"
    written = files_of(split)
    time.sleep(0.5)
    assert files_of(split) == written  # nobody writes any more
    resumed = generate(out, "--resume", workers=2)
    _, err = resumed.communicate(timeout=120)
    assert resumed.returncode == 0, err.decode()
    assert files_of(split) == reference["files"]
    assert (split / MANIFEST_NAME).read_bytes() == reference["manifest"]


@pytest.mark.parametrize("mode", ["", "--resume", "--overwrite"])
def test_a_second_run_on_a_split_being_written_is_refused_and_harms_nothing(tmp_path, reference, mode):
    """While one generate writes a split, the same command (with or without --resume or
    --overwrite) is refused in one line, deletes nothing (no .partial file of the first
    run), and the first run completes with the reference bytes."""
    out = tmp_path / "busy"
    split = out / "toaster" / "train"
    first = generate(out)
    while first.poll() is None and not list(split.glob("shard-*.h5")):
        time.sleep(POLL_S)
    assert first.poll() is None, "the first run ended before the second could start"
    second = generate(out, *([mode] if mode else []))
    _, err = second.communicate(timeout=120)
    lines = err.decode().strip().splitlines()
    if second.returncode == 0:
        # allowed only if the first run had already finished its split (it releases the lock before
        # its process exits): the second then found a complete split. Both must leave the reference bytes.
        _, err1 = first.communicate(timeout=120)
        assert first.returncode == 0, err1.decode()
        assert files_of(split) == reference["files"]
        assert (split / MANIFEST_NAME).read_bytes() == reference["manifest"]
        pytest.skip("the first run had finished its split before the second started (a fast machine): no overlap")
    # without a flag the split's existing shards may be found before the lock: either refusal is right
    expected = ("another artdata generate",) + (("already holds generated data",) if not mode else ())
    assert second.returncode == 2 and len(lines) == 1 and any(e in lines[0] for e in expected), err.decode()
    _, err = first.communicate(timeout=120)
    assert first.returncode == 0, err.decode()
    assert files_of(split) == reference["files"]
    assert (split / MANIFEST_NAME).read_bytes() == reference["manifest"]
