"""Every ```bash and ```python block of README.md and docs/*.md runs, as a reader would run it.

The blocks of one page run in order, in one temporary folder (a page is read top to bottom:
a later block may use what an earlier one wrote), python blocks saved as a script and run with
``python block.py`` (so a missing ``if __name__ == "__main__"`` guard fails as it does for a
user), bash blocks with ``bash -e -o pipefail``.  The folder starts with the files the docs'
examples name, on tiny data:

* ``data/<class>/{train,test}`` for every registered class (2 objects x 2 images each);
* ``preds.h5``: the mean baseline's predictions for ``data/cabinet/test``.

A block that must not run here is marked, on the line before its fence, with
``<!-- no-test: REASON -->`` (or ``skip-test`` in its info string, ```` ```bash skip-test ````,
with the reason in the text): paper-scale runs, installers, a cluster, downloads, timing
benchmarks and API synopses whose names are placeholders.  A marker without a reason fails.
Blocks that need the shipped model weights (``--model dense``, ``ad.estimate``,
``make_estimator("dense", ...)``) run when ``articulated_dataset.methods.shipped_models()``
lists any, and are skipped otherwise.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from helpers_core import ROOT

PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
#: Objects and images per object of each tiny split the blocks run on.
TINY_OBJECTS, TINY_IMAGES = 2, 2
#: Blocks marked no-test, at most (11 of 21 today: 3 paper-scale or installer blocks in README,
#: 3 Ray-cluster, 3 timing benchmarks or downloads, 2 API synopses); raise it only with a reason.
MAX_MARKED = 11
#: Seconds one block may take before it counts as failed (the whole file runs in ~1-2 min).
BLOCK_TIMEOUT_S = 300

FENCE = re.compile(r"^```(?P<lang>bash|python)(?P<info>[^\n]*)\n(?P<code>.*?)^```[ \t]*$", re.S | re.M)
NO_TEST = re.compile(r"<!--\s*no-test(?::\s*(?P<reason>.*?))?\s*-->\s*$")
NEEDS_WEIGHTS = re.compile(r"--model dense\b|\bad\.estimate\(|make_estimator\(\s*[\"']dense[\"']")


@dataclass
class Block:
    page: Path
    line: int  # of the opening fence, 1-based
    lang: str
    code: str
    skip_reason: str | None  # None: runs

    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def page_blocks(page: Path) -> list[Block]:
    text = page.read_text()
    out = []
    for m in FENCE.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        before = text[: m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        marker = NO_TEST.search(before)
        reason = None
        if marker is not None:
            reason = marker.group("reason") or ""
        elif "skip-test" in m.group("info").split():
            reason = "marked skip-test"
        out.append(Block(page, line, m.group("lang"), m.group("code"), reason))
    return out


def all_blocks() -> list[Block]:
    return [b for page in PAGES for b in page_blocks(page)]


def test_every_skip_marker_gives_a_reason():
    blocks = all_blocks()
    assert blocks, "no code blocks found"
    unexplained = [b.where() for b in blocks if b.skip_reason is not None and len(b.skip_reason.strip()) < 8]
    assert not unexplained, f"<!-- no-test: REASON --> needs a reason: {unexplained}"
    skipped = [b.where() for b in blocks if b.skip_reason is not None]
    assert len(skipped) <= MAX_MARKED, f"{len(skipped)} blocks marked no-test (at most {MAX_MARKED}): {skipped}"


@pytest.fixture(scope="session")
def docs_workdir(tmp_path_factory) -> Path:
    """The folder every page's run starts from (copied per page)."""
    from articulated_dataset.classes.registry import class_names
    from articulated_dataset.generation import GenerationConfig, generate_split

    base = tmp_path_factory.mktemp("docs-base")
    for name in class_names():
        for split in ("train", "test"):
            generate_split(GenerationConfig(name, split=split, n_objects=TINY_OBJECTS, images_per_object=TINY_IMAGES),
                           base / "data")
    run_cli(["baseline", "mean", "--train", "data/cabinet/train", "--test", "data/cabinet/test", "--out", "preds.h5",
             "-q"], cwd=base)
    return base


def block_env() -> dict:
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])  # this environment's artdata
    env.setdefault("OMP_NUM_THREADS", "1")
    env["MPLBACKEND"] = "Agg"
    return env


def run_cli(args: list[str], cwd: Path) -> None:
    res = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", *args], cwd=cwd, env=block_env(),
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def has_shipped_weights() -> bool:
    from articulated_dataset.methods import shipped_models

    return bool(shipped_models())


PAGES_WITH_BLOCKS = [p for p in PAGES if page_blocks(p)]


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES_WITH_BLOCKS, ids=[str(p.relative_to(ROOT)) for p in PAGES_WITH_BLOCKS])
def test_page_code_blocks_run(page, docs_workdir, tmp_path):
    blocks = page_blocks(page)
    weights = None
    runnable = []
    for b in blocks:
        if b.skip_reason is None and NEEDS_WEIGHTS.search(b.code):
            weights = has_shipped_weights() if weights is None else weights
            if not weights:
                b.skip_reason = "needs the shipped model weights (none in articulated_dataset/methods/weights)"
        if b.skip_reason is None:
            runnable.append(b)
    if not runnable:
        pytest.skip(f"every block is marked no-test or needs the shipped weights: {[b.skip_reason for b in blocks]}")
    work = tmp_path / "work"
    shutil.copytree(docs_workdir, work, symlinks=True)
    for k, b in enumerate(runnable):
        script = work.parent / f"block{k}.{'py' if b.lang == 'python' else 'sh'}"
        script.write_text(b.code)
        cmd = [sys.executable, str(script)] if b.lang == "python" else ["bash", "-e", "-o", "pipefail", str(script)]
        try:
            res = subprocess.run(cmd, cwd=work, env=block_env(), capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{b.where()}: still running after {BLOCK_TIMEOUT_S} s")
        assert res.returncode == 0, (f"{b.where()} ({b.lang}) exited {res.returncode}:\n{b.code}\n--- stdout\n"
                                     f"{res.stdout[-3000:]}\n--- stderr\n{res.stderr[-3000:]}")
