"""The README stays true and the package works when installed from a wheel (non-editable);
its metadata (dependencies, version, citation, dataset card) says what is true."""

import ast
import os
import re
import shutil
import subprocess
import sys
import zipfile
from importlib.metadata import PackageNotFoundError, distribution, packages_distributions, version
from pathlib import Path

import pytest
import tomllib
import yaml

import articulated_dataset
from articulated_dataset.classes.registry import all_classes
from helpers_core import ROOT


def test_readme_lists_every_registered_class():
    readme = (ROOT / "README.md").read_text()
    for c in all_classes():
        assert re.search(rf"^\| {c.name} \|", readme, re.M), c.name


def test_ci_runs_the_readme_test_command():
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", readme, re.S)
    test_cmd = blocks[1].strip()
    assert test_cmd in (ROOT / ".ci" / "run").read_text()
    assert "artdata generate" in blocks[0] and "scripts/setup.sh" in blocks[0]


def source_copy(dest: Path) -> Path:
    """The checkout's files (tracked, and untracked ones git does not ignore) copied to ``dest``:
    the package is built there, so a build never leaves a ``build/`` folder in the checkout (one
    there shadows the ``build`` module for ``python -m build`` run from the checkout)."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for rel in filter(None, listed):
        src = ROOT / rel
        if src.is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / rel)
    return dest


@pytest.mark.slow
def test_wheel_ships_class_folders(tmp_path):
    before = sorted(p.name for p in ROOT.iterdir())
    src = source_copy(tmp_path / "src")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path), str(src)],
                   check=True, capture_output=True, cwd=tmp_path)
    assert sorted(p.name for p in ROOT.iterdir()) == before  # built in the copy: no build/ in the checkout
    wheel = next(tmp_path.glob("articulated_dataset-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for c in all_classes():
        assert f"articulated_dataset/classes/{c.name}/{c.template}" in names
        assert f"articulated_dataset/classes/{c.name}/__init__.py" in names
        assert f"articulated_dataset/classes/{c.name}/README.md" in names
    assert "articulated_dataset/classes/common.xacro" in names
    tracked = subprocess.run(["git", "ls-files", "articulated_dataset/methods/weights"], cwd=ROOT, capture_output=True, text=True)
    for w in tracked.stdout.split():  # the shipped weights and models.json (once committed)
        assert w in names, w
    # Installed non-editable into a separate folder and imported from elsewhere, the
    # registry still finds every class and its template expands.
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
                   check=True, capture_output=True)
    code = ("import articulated_dataset.classes.registry as r, articulated_dataset.generation.templating as t;"
            "cs = r.all_classes(); assert str(cs[0].template_path()).startswith(%r);"
            "print(len(cs), len(t.render_urdf(cs[0].template_path(), {})))" % str(target))
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"},
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[0] == str(len(all_classes()))


def test_every_subpackage_is_packaged():
    """Packages are found by setuptools (``[tool.setuptools.packages.find]``), which finds only
    folders with an ``__init__.py``: a folder of modules without one would be left out of the wheel."""
    find = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    assert find["include"] == ["articulated_dataset*"]
    folders = {p.parent for p in (ROOT / "articulated_dataset").rglob("*.py") if "__pycache__" not in p.parts}
    missing = sorted(str(f.relative_to(ROOT)) for f in folders if not (f / "__init__.py").is_file())
    assert missing == [], f"folders of modules without __init__.py (not packaged): {missing}"


@pytest.mark.slow
def test_sdist_ships_class_folders_and_weights(tmp_path):
    """The sdist (what `python -m build` builds the wheel from in .ci/run) carries the class folders
    (templates, READMEs, CHANGELOGs), every tracked weight file and every subpackage."""
    src = source_copy(tmp_path / "src")
    res = subprocess.run([sys.executable, "-m", "build", "--sdist", "--no-isolation", "--outdir", str(tmp_path), str(src)],
                         capture_output=True, text=True, cwd=tmp_path)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    import tarfile

    sdist = next(tmp_path.glob("articulated_dataset-*.tar.gz"))
    with tarfile.open(sdist) as tar:
        names = {n.split("/", 1)[1] for n in tar.getnames() if "/" in n}
    want = [p.relative_to(ROOT).as_posix() for p in (ROOT / "articulated_dataset" / "classes").rglob("*")
            if p.suffix in (".xacro", ".md")]
    want += [p.relative_to(ROOT).as_posix() for p in (ROOT / "articulated_dataset").rglob("__init__.py")
             if "__pycache__" not in p.parts]
    tracked = subprocess.run(["git", "ls-files", "articulated_dataset/methods/weights"], cwd=ROOT, capture_output=True, text=True)
    want += tracked.stdout.split()
    missing = [w for w in want if w not in names]
    assert not missing, missing
    ci = (ROOT / ".ci" / "run").read_text()  # CI builds both, installs the wheel in a fresh venv, generates, scores
    assert "python3 -m build" in ci and "-m venv" in ci and '/artdata" generate' in ci and '/artdata" score' in ci


# --------------------------------------------------------------------------------------
# metadata

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
#: Distributions listed without being imported by the package's own code, and why.
IMPORTED_BY_OTHERS = {"pyopengl": "mujoco.egl / mujoco.osmesa import it for offscreen contexts"}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_names(reqs) -> set[str]:
    return {_norm(re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0]) for r in reqs}


def _imported_distributions() -> dict[str, set[str]]:
    """{third-party module the package imports: the distributions providing it}."""
    mods = set()
    for path in (ROOT / "articulated_dataset").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                mods |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                mods.add(node.module.split(".")[0])
    mods -= set(sys.stdlib_module_names) | {"articulated_dataset", "__future__"}
    dists = packages_distributions()
    for m in mods - set(dists):  # extension modules (OpenEXR.so) may be missing from that map
        try:
            dists[m] = [distribution(m).metadata["Name"]]
        except PackageNotFoundError:
            pass
    unknown = sorted(m for m in mods if m not in dists)
    assert not unknown, f"imported but not installed: {unknown}"
    return {m: {_norm(d) for d in dists[m]} for m in mods}


@pytest.mark.slow
def test_dependencies_are_what_the_package_imports():
    core = _requirement_names(PYPROJECT["project"]["dependencies"])
    extras = {k: _requirement_names(v) for k, v in PYPROJECT["project"]["optional-dependencies"].items()}
    optional = set().union(*extras.values())
    imported = _imported_distributions()
    # torch, jax, grain, ray, scipy: optional, imported only where needed (one-line errors otherwise);
    # absl comes with grain (the JAX loader marks its flags parsed for grain's workers)
    unlisted = sorted(m for m, d in imported.items() if not d & (core | optional | {"absl-py"}))
    assert not unlisted, f"imported by the package but in no dependency list: {unlisted}"
    used = set().union(*imported.values())
    unused = sorted(d for d in core if d not in used and d not in IMPORTED_BY_OTHERS)
    assert not unused, f"core dependencies the package never imports: {unused}"
    assert "pyrender-maintained" not in core and "pyrender-maintained" in extras["test"]  # test-only cross-check
    assert {"torch", "jax", "grain", "ray", "scipy"} <= optional and not ({"torch", "jax", "grain", "ray"} & core)


def test_version_is_defined_once():
    v = articulated_dataset.__version__
    assert "version" not in PYPROJECT["project"] and "version" in PYPROJECT["project"]["dynamic"]
    assert PYPROJECT["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "articulated_dataset.__version__"}
    assert version("articulated_dataset") == v  # what the installed metadata says
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert "## [Unreleased]" in changelog and re.search(rf"^## \[{re.escape(v)}\]", changelog, re.M)
    assert yaml.safe_load((ROOT / "CITATION.cff").read_text())["version"] == v


def test_citation_cites_the_paper_and_the_package():
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0" and cff["type"] == "software" and "articulated_dataset" in cff["title"]
    assert cff["license"] == "MIT" and cff["authors"]
    paper = cff["preferred-citation"]
    assert paper["title"] == "Learning to Generalize Kinematic Models to Novel Objects" and paper["year"] == 2019
    assert [a["family-names"] for a in paper["authors"]] == ["Abbatematteo", "Tellex", "Konidaris"]
    assert "CoRL" in paper["conference"]["name"]


def test_datasheet_has_a_dataset_card_metadata_block():
    text = (ROOT / "DATASHEET.md").read_text()
    assert text.startswith("---\n")
    meta = yaml.safe_load(text.split("---\n", 2)[1])
    assert meta["license"] == "mit" and meta["pretty_name"]
    assert meta["size_categories"] == ["1M<n<10M"]  # 1,056,000 images at the paper's size
    assert {"depth-estimation", "robotics"} <= set(meta["task_categories"])
    assert meta["annotations_creators"] == ["machine-generated"]
    assert text.split("---\n", 2)[2].lstrip().startswith("# Datasheet")


def test_setup_script_options():
    setup = ROOT / "scripts" / "setup.sh"
    assert subprocess.run(["bash", "-n", str(setup)]).returncode == 0
    for args in (["--bogus"], ["--venv"]):
        res = subprocess.run(["bash", str(setup), *args], capture_output=True, text=True)
        assert res.returncode == 2 and res.stderr.count("\n") == 1 and res.stderr.startswith("setup: "), args
    res = subprocess.run(["bash", str(setup), "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and all(opt in res.stdout for opt in ("--venv", "--all", "--yes"))
    text = setup.read_text()
    assert "https://download.pytorch.org/whl/cpu" in text and "torch==$TORCH_VERSION" in text


def test_setup_script_asks_before_apt_get(tmp_path):
    """Without a terminal to ask and without --yes, setup.sh names the packages and the command to
    run, and installs nothing (here no rendering library is found: ldconfig lists none)."""
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "ldconfig").write_text("#!/bin/sh\nexit 0\n")
    (fake / "ldconfig").chmod(0o755)
    res = subprocess.run(["bash", str(ROOT / "scripts" / "setup.sh")], capture_output=True, text=True,
                         stdin=subprocess.DEVNULL, env={**os.environ, "PATH": f"{fake}:{os.environ['PATH']}"})
    assert res.returncode == 1, res.stdout + res.stderr
    assert "will install" in res.stdout and "libegl1" in res.stdout and "[1/3]" not in res.stdout
    assert res.stderr.count("\n") == 1 and "--yes" in res.stderr and "apt-get install -y libegl1" in res.stderr
