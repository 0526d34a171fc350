"""Third-party URDFs from strangers: never evaluated, meshes only from the URDF's folder, sane numbers.

Every case runs ``artdata generate --urdf`` (or a command that rebuilds a stored third-party
object) as a user does on a crafted file and checks that the command ends with exactly one line
``artdata: error: ...`` and exit code 2, that nothing outside the named folders changed (the
whole test folder, with a ``victim/`` folder of canary files, compared byte for byte; only the
processed-URDF cache may change) and that no injected payload ran (each would create a file
``PWNED`` if evaluated).  Where a reference would *succeed* if followed (a valid mesh placed where
it points), following it would pass silently, so these tables fail on it.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from articulated_dataset.core.errors import UserError
from articulated_dataset.format import MANIFEST_NAME
from articulated_dataset.generation import GenerationConfig, generate_split, urdf_import
from articulated_dataset.generation.templating import render_urdf
from helpers_core import PWNED, GuardedFolder, assert_one_line_error, edit_json, run_cli

# --------------------------------------------------------------------------------------
# 5. third-party URDFs: never evaluated, meshes only from the URDF's folder, sane numbers
# --------------------------------------------------------------------------------------

def _payloads(pwned: Path) -> dict[str, str]:
    """Strings that create ``pwned`` if xacro (or Python) ever evaluates them."""
    return {
        # xacro's dunder check does not look inside comprehensions
        "comprehension": ("${[c.__init__.__globals__['system']('touch " + str(pwned) + "') for x in [1] "
                          "for c in x.__class__.__base__.__subclasses__() if c.__name__ == '_wrap_close']}"),
        "eval": "$(eval __import__('os').system('touch " + str(pwned) + "'))",
        "import": "${__import__('os').system('touch " + str(pwned) + "')}",
    }


OBJ_D = 0.4  # m: body cube side of the test object


def _urdf_folder(guarded) -> Path:
    folder = guarded.root / "obj"
    folder.mkdir()
    body = trimesh.creation.box(extents=[OBJ_D] * 3)
    body.apply_translation([0, 0, OBJ_D / 2])
    body.export(str(folder / "body.obj"))
    door = trimesh.creation.box(extents=[0.02, OBJ_D, OBJ_D])
    door.apply_translation([-0.01, -OBJ_D / 2, OBJ_D / 2])
    door.export(str(folder / "door.obj"))
    return folder


def _urdf(robot="obj", base="base", door="door", joint="hinge", parent=None, child=None, body_mesh="body.obj",
          door_geom='<mesh filename="door.obj"/>', joint_type="revolute", limit='lower="0" upper="1.5"',
          origin='xyz="-0.2 0.2 0"', axis="0 0 -1", extra_link="", visual_name="", material="", mimic="",
          door_origin="") -> str:
    parent = base if parent is None else parent
    child = door if child is None else child
    limit_xml = f"<limit {limit} effort=\"1\" velocity=\"1\"/>" if limit is not None else ""
    return (f'<?xml version="1.0"?>\n<robot name="{robot}">'
            f'<link name="{base}"><visual{visual_name}><geometry><mesh filename="{body_mesh}"/></geometry>{material}'
            f'</visual></link>'
            f'<link name="{door}"><visual>{door_origin}<geometry>{door_geom}</geometry></visual></link>{extra_link}'
            f'<joint name="{joint}" type="{joint_type}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin {origin}/><axis xyz="{axis}"/>{limit_xml}{mimic}</joint></robot>\n')


def _generate_urdf(guarded, text: str, *extra, name="obj.urdf"):
    folder = guarded.root / "obj" if (guarded.root / "obj").is_dir() else _urdf_folder(guarded)
    path = folder / name
    path.write_text(text, encoding="utf-8")
    guarded.freeze()
    return run_cli("generate", "--urdf", path, "--n", 1, "--images", 1, "--out", guarded.root / "out", "-q", *extra)


@pytest.fixture
def urdf_world(guarded, monkeypatch):
    monkeypatch.setenv(urdf_import.CACHE_ENV, str(guarded.root / "cache"))
    return guarded


@pytest.mark.slow
def test_the_test_object_generates(urdf_world):
    """Control: the unmodified object generates, so each refusal below is caused by its change."""
    result = _generate_urdf(urdf_world, _urdf())
    assert result.exit_code == 0, result.output
    assert (urdf_world.root / "out" / "obj-obj" / "train" / MANIFEST_NAME).is_file()


NAME_FIELDS = ["joint", "base", "door", "parent", "child"]


@pytest.mark.parametrize("field", NAME_FIELDS)
@pytest.mark.parametrize("payload", ["comprehension", "eval", "import"])
def test_injection_in_names_is_refused_never_run(urdf_world, field, payload):
    text = _payloads(urdf_world.root / PWNED)[payload].replace('"', "&quot;")
    assert_one_line_error(_generate_urdf(urdf_world, _urdf(**{field: text})))
    urdf_world.assert_untouched()


@pytest.mark.parametrize("field, extra", [("body_mesh", ["--skip-missing-meshes"]), ("robot", []), ("material", []),
                                          ("visual_name", [])])
def test_injection_where_names_are_not_used_stays_inert(urdf_world, field, extra):
    """Text that never becomes a name is carried as data: the object generates, nothing runs."""
    text = _payloads(urdf_world.root / PWNED)["comprehension"].replace('"', "&quot;")
    value = {"material": f'<material name="{text}"/>', "visual_name": f' name="{text}"'}.get(field, text)
    result = _generate_urdf(urdf_world, _urdf(**{field: value}), *extra)
    if field == "body_mesh":  # the body has no geometry left: refused, nothing ran
        assert_one_line_error(result, "no geometry")
    else:
        assert result.exit_code == 0, result.output
    assert not list(urdf_world.root.rglob(PWNED))


BAD_NAMES = {"space": "a b", "quote": "a&quot;b", "newline": "a&#10;b", "brace": "a{b}", "dollar": "a$b",
             "unicode": "门", "long": "j" * 200, "dot-start": ".j", "dash-start": "-j", "backtick": "a`b`"}


@pytest.mark.parametrize("field", ["joint", "door"])
@pytest.mark.parametrize("bad", list(BAD_NAMES))
def test_names_must_be_identifiers(urdf_world, field, bad):
    assert_one_line_error(_generate_urdf(urdf_world, _urdf(**{field: BAD_NAMES[bad]})), "name")
    urdf_world.assert_untouched()


def test_plain_urdf_is_never_expanded(tmp_path):
    """The templating stage returns a plain URDF as it is: nothing in it is evaluated."""
    text = _urdf(joint=_payloads(tmp_path / PWNED)["comprehension"].replace('"', "&quot;"))
    (tmp_path / "model.urdf").write_text(text)
    assert render_urdf(tmp_path / "model.urdf", {"x": "1"}) == text
    assert not (tmp_path / PWNED).exists()


XML_ATTACKS = {
    "xxe-file": ('<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY x SYSTEM "file://{victim}/canary.txt">]>\n', "&x;"),
    "entity-bomb": ('<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;">]>\n',
                    "&b;"),
    "xxe-param": ('<?xml version="1.0"?>\n<!DOCTYPE robot [<!ENTITY % p SYSTEM "file://{victim}/canary.txt"> %p;]>\n',
                  "hinge"),
}


@pytest.mark.parametrize("attack", list(XML_ATTACKS))
def test_xml_entities_are_refused(urdf_world, attack):
    head, name = XML_ATTACKS[attack]
    body = _urdf(joint=name).split("\n", 1)[1]
    result = _generate_urdf(urdf_world, head.format(victim=urdf_world.victim) + body)
    assert_one_line_error(result)
    urdf_world.assert_untouched()


def test_xinclude_is_not_processed(urdf_world):
    """An XInclude element is an unknown element, never followed: the joint it would bring is missing."""
    text = _urdf().replace("<joint ", '<xi:include xmlns:xi="http://www.w3.org/2001/XInclude" href="joint.xml"/><j ')
    text = text.replace("</joint>", "</j>")
    assert_one_line_error(_generate_urdf(urdf_world, text))
    urdf_world.assert_untouched()


def _mesh_outside(guarded) -> Path:
    guarded.victim.mkdir(exist_ok=True)
    m = trimesh.creation.box(extents=[0.02, OBJ_D, OBJ_D])
    m.apply_translation([-0.01, -OBJ_D / 2, OBJ_D / 2])
    m.export(str(guarded.victim / "door.obj"))
    return guarded.victim / "door.obj"


MESH_REFS = ["../victim/door.obj", "{abs}", "file://{abs}", "package://../victim/door.obj", "link.obj",
             "sub/../../victim/door.obj"]


@pytest.mark.parametrize("ref", MESH_REFS)
def test_meshes_only_from_the_urdf_folder(urdf_world, ref):
    outside = _mesh_outside(urdf_world)
    folder = _urdf_folder(urdf_world)
    (folder / "link.obj").symlink_to(outside)
    (folder / "sub").mkdir()
    ref = ref.replace("{abs}", str(outside))
    assert_one_line_error(_generate_urdf(urdf_world, _urdf(door_geom=f'<mesh filename="{ref}"/>')), "lies outside")
    urdf_world.assert_untouched()


def test_mesh_root_allows_a_named_folder(urdf_world):
    _mesh_outside(urdf_world)
    result = _generate_urdf(urdf_world, _urdf(door_geom='<mesh filename="../victim/door.obj"/>'),
                            "--mesh-root", urdf_world.root)
    assert result.exit_code == 0, result.output


ABSURD = {
    "mesh-scale-zero": dict(door_geom='<mesh filename="door.obj" scale="0 0 0"/>'),
    "mesh-scale-one-zero": dict(door_geom='<mesh filename="door.obj" scale="1 0 1"/>'),
    "mesh-scale-nan": dict(door_geom='<mesh filename="door.obj" scale="nan nan nan"/>'),
    "mesh-scale-inf": dict(door_geom='<mesh filename="door.obj" scale="1 inf 1"/>'),
    "box-negative": dict(door_geom='<box size="-0.02 0.4 0.4"/>'),
    "box-zero": dict(door_geom='<box size="0 0.4 0.4"/>'),
    "box-nan": dict(door_geom='<box size="nan 0.4 0.4"/>'),
    "box-overflow": dict(door_geom='<box size="1e400 0.4 0.4"/>'),
    "cylinder-negative": dict(door_geom='<cylinder radius="-0.1" length="0.4"/>'),
    "cylinder-zero-length": dict(door_geom='<cylinder radius="0.1" length="0"/>'),
    "sphere-negative": dict(door_geom='<sphere radius="-0.1"/>'),
    "joint-origin-nan": dict(origin='xyz="nan 0.2 0"'),
    "joint-origin-overflow": dict(origin='xyz="1e400 0.2 0"'),
    "joint-rpy-nan": dict(origin='xyz="-0.2 0.2 0" rpy="nan 0 0"'),
    "visual-origin-nan": dict(door_origin='<origin xyz="0 nan 0"/>'),
    "limit-1e30": dict(limit='lower="0" upper="1e30"'),
    "limit-minus-1e30": dict(limit='lower="-1e30" upper="0"'),
    "limit-nan": dict(limit='lower="0" upper="nan"'),
    "limit-inf": dict(limit='lower="0" upper="inf"'),
    "prismatic-1e30": dict(joint_type="prismatic", axis="-1 0 0", limit='lower="0" upper="1e30"'),
    "prismatic-100m": dict(joint_type="prismatic", axis="-1 0 0", limit='lower="0" upper="100"'),
    "axis-zero": dict(axis="0 0 0"),
    "axis-nan": dict(axis="nan 0 1"),
    "object-too-big": dict(door_geom='<box size="0.02 400 400"/>'),
    "empty-range": dict(limit='lower="1" upper="1"'),
    "no-limit": dict(limit=None),
}


@pytest.mark.parametrize("case", list(ABSURD))
def test_absurd_numbers_are_one_line(urdf_world, case):
    extra = ["--joints", "hinge"] if case in ("empty-range",) else []
    assert_one_line_error(_generate_urdf(urdf_world, _urdf(**ABSURD[case]), *extra))
    urdf_world.assert_untouched()


@pytest.mark.parametrize("scale", ["0", "-1", "nan", "inf", "1e6", "1e-6", "abc"])
def test_bad_scale(urdf_world, scale):
    assert_one_line_error(_generate_urdf(urdf_world, _urdf(), "--scale", scale))
    urdf_world.assert_untouched()


def _mesh_file(guarded, name: str, content: bytes | None = None, mesh=None) -> str:
    folder = guarded.root / "obj" if (guarded.root / "obj").is_dir() else _urdf_folder(guarded)
    if mesh is not None:
        mesh.export(str(folder / name))
    else:
        (folder / name).write_bytes(content)
    return name


def _many_faces() -> trimesh.Trimesh:
    """A mesh of 110,000 triangles (220,000 once double-sided): over MuJoCo's STL limit."""
    n = 110_000
    rng = np.random.default_rng(0)
    v = rng.uniform(-0.2, 0.2, (3 * n, 3)) + [0, 0, 0.2]
    return trimesh.Trimesh(v, np.arange(3 * n).reshape(n, 3), process=False)


MESH_FILES = {
    "nan-vertex": (b"v nan 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n", None, "not finite"),
    "no-triangles": (b"v 0 0 0\nv 1 0 0\n", None, "no triangles"),
    "garbage": (bytes(range(256)) * 4, None, "mesh file"),
    "too-many-faces": (None, _many_faces, "MuJoCo"),
}


@pytest.mark.parametrize("case", list(MESH_FILES))
def test_bad_meshes(urdf_world, case):
    content, make, needle = MESH_FILES[case]
    suffix = ".stl" if make else ".obj"
    name = _mesh_file(urdf_world, "bad" + suffix, content, make() if make else None)
    assert_one_line_error(_generate_urdf(urdf_world, _urdf(door_geom=f'<mesh filename="{name}"/>')), needle)
    urdf_world.assert_untouched()


@pytest.mark.parametrize("buffer", ["fifo", "directory"])
def test_a_mesh_buffer_that_is_not_a_regular_file(urdf_world, buffer):
    """A glTF inside the URDF's folder naming a FIFO as its buffer is refused, not read forever
    (the mesh file itself and the files it names must be regular files)."""
    import threading

    folder = _urdf_folder(urdf_world)
    door = trimesh.creation.box(extents=[0.02, OBJ_D, OBJ_D])
    door.apply_translation([-0.01, -OBJ_D / 2, OBJ_D / 2])
    gltf = json.loads(trimesh.exchange.gltf.export_gltf(trimesh.Scene(door))["model.gltf"])
    gltf["buffers"][0]["uri"] = "door.bin"
    (folder / "door.gltf").write_text(json.dumps(gltf))
    if buffer == "fifo":
        os.mkfifo(folder / "door.bin")
    else:
        (folder / "door.bin").mkdir()
    result = []
    worker = threading.Thread(target=lambda: result.append(
        _generate_urdf(urdf_world, _urdf(door_geom='<mesh filename="door.gltf"/>'))), daemon=True)
    worker.start()
    worker.join(60)
    if worker.is_alive():  # unblock the reader so the test process can end
        with open(folder / "door.bin", "wb"):
            pass
        worker.join(10)
        pytest.fail("reading the mesh's buffer blocked")
    assert_one_line_error(result[0], "door.gltf")
    urdf_world.assert_untouched()


@pytest.mark.parametrize("class_name", ["../x", "/tmp/x", "..", ".x", "-x", "a/b", "x" * 40, "${1}"])
def test_class_name_option_is_a_name(urdf_world, class_name):
    assert_one_line_error(_generate_urdf(urdf_world, _urdf(), "--class-name", class_name), "class name")
    urdf_world.assert_untouched()


def test_continuous_joints_are_not_chosen_by_default(urdf_world):
    line = assert_one_line_error(_generate_urdf(urdf_world, _urdf(joint_type="continuous", limit=None)))
    assert "--joints" in line
    urdf_world.assert_untouched()


def test_not_a_robot(urdf_world):
    assert_one_line_error(_generate_urdf(urdf_world, '<?xml version="1.0"?>\n<mujoco><include file="/etc/passwd"/></mujoco>\n'),
                   "not a URDF")



# --------------------------------------------------------------------------------------
# 6. rebuilding a stored third-party object reads the definition back safely
# --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def urdf_split(tmp_path_factory):
    root = tmp_path_factory.mktemp("third-party-urdf")
    old = os.environ.get(urdf_import.CACHE_ENV)
    os.environ[urdf_import.CACHE_ENV] = str(root / "cache")
    guarded = GuardedFolder(root / "w")
    folder = _urdf_folder(guarded)
    (folder / "obj.urdf").write_text(_urdf())
    obj = urdf_import.import_urdf(folder / "obj.urdf", class_name="foreign")
    split = generate_split(GenerationConfig("foreign", n_objects=1, images_per_object=1, third_party=obj.definition),
                           root / "data")
    yield {"split": split, "folder": folder}
    if old is None:
        os.environ.pop(urdf_import.CACHE_ENV, None)
    else:
        os.environ[urdf_import.CACHE_ENV] = old


def _source_sha256(urdf: Path, meshes=("body.obj", "door.obj")) -> str:
    """The sha256 a definition records (urdf_import.parse.source_digest), computed independently."""
    import hashlib

    h = hashlib.sha256(urdf.read_bytes())
    for name in sorted(meshes):
        h.update(name.encode())
        h.update((urdf.parent / name).read_bytes())
    return h.hexdigest()


def _definition_edit(key, value, folder: Path, pwned: Path):
    def edit(m):
        d = m["config"]["third_party"]
        if key == "urdf-payload":  # an injected joint name in the URDF the definition names, with its true sha256
            payload = _payloads(pwned)["comprehension"]
            (folder / "evil.urdf").write_text(_urdf(joint=payload.replace('"', "&quot;")))
            d["urdf"], d["joints"], d["sha256"] = str(folder / "evil.urdf"), [payload], _source_sha256(folder / "evil.urdf")
        else:
            d[key] = value
    return edit


DEFINITION_CASES = [("urdf-payload", None), ("class_name", "../../x"), ("urdf", "relative.urdf"),
                    ("sha256", "0" * 64), ("sha256", "x"), ("scale", -1), ("mesh_root", "rel"), ("camera", "wide"),
                    ("joints", "hinge"), ("unknown_key", 1)]


@pytest.mark.parametrize("how", ["show-rgb", "plan-simulate"])
@pytest.mark.parametrize("key, value", DEFINITION_CASES, ids=[f"{k}-{i}" for i, (k, _) in enumerate(DEFINITION_CASES)])
def test_rebuild_reads_the_definition_safely(urdf_split, tmp_path, how, key, value):
    guarded = GuardedFolder(tmp_path)
    split = guarded.root / "data" / "foreign" / "train"
    shutil.copytree(urdf_split["split"], split)
    edit_json(split / MANIFEST_NAME, _definition_edit(key, value, urdf_split["folder"], guarded.root / PWNED))
    guarded.freeze()
    if how == "show-rgb":
        result = run_cli("show", split, "--rgb", "--n", 1, "--out", guarded.root / "out.png", "-q")
    else:
        result = run_cli("plan", split, "--index", 0, "--simulate", "-q")
    assert_one_line_error(result)
    guarded.assert_untouched()
    assert not (urdf_split["folder"] / PWNED).exists()


def test_rebuilt_definition_checked_by_the_library(urdf_split):
    from articulated_dataset.format import read_manifest

    cfg = read_manifest(urdf_split["split"])["config"]
    cfg["third_party"]["class_name"] = "../x"
    with pytest.raises(UserError, match="corrupt third-party URDF definition"):
        GenerationConfig.from_dict(cfg).obj_class  # noqa: B018 - the property reads and checks



# --------------------------------------------------------------------------------------
# 7. as a real process: nothing else reaches stderr (library logs, numpy warnings)
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["missing-mesh", "inf-origin"])  # a yourdfpy log line, numpy/trimesh warnings
def test_stderr_is_one_line_in_a_real_process(guarded, case):
    """CliRunner does not see what logging handlers and Python warnings write to the real
    stderr; a subprocess does."""
    import subprocess
    import sys

    _urdf_folder(guarded)
    text = {"missing-mesh": _urdf(door_geom='<mesh filename="nothere.obj"/>'),
            "inf-origin": _urdf(origin='xyz="1e400 0 0" rpy="1e400 0 0"')}[case]
    (guarded.root / "obj" / "obj.urdf").write_text(text)
    args = ["generate", "--urdf", str(guarded.root / "obj" / "obj.urdf"), "--n", "1", "--out", str(guarded.root / "out"), "-q"]
    env = {**os.environ, urdf_import.CACHE_ENV: str(guarded.root / "cache"), "PYTHONWARNINGS": "default"}
    guarded.freeze()
    proc = subprocess.run([sys.executable, "-m", "articulated_dataset.cli", *args], capture_output=True, text=True,
                          env=env, timeout=120)
    assert_one_line_error(proc)
    guarded.assert_untouched()

