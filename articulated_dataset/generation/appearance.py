"""Colour images (``artdata generate --rgb``): randomised materials, textures and lights.

The colour image is rendered with the same model, state and camera as the depth and mask,
right after them (the occluders as drawn for that image), so its object pixels are exactly
the pixels the depth has (the background is black, (0, 0, 0); no object pixel is, because
every material and light has a floor, :data:`APPEARANCE_TABLE`).  Textures, materials and
lights never change the depth or the mask (both come from the segmentation pass): an
``--rgb`` split's depth, mask and labels are those of the same split without it.

What is drawn, from the object's own stream (:data:`APPEARANCE_STREAM`, a further child of
its SeedSequence: the default streams and bytes are untouched), uniformly within
:data:`APPEARANCE_TABLE`:

* per object (each compiled pose): one material per mask code -- the body, each moving part,
  the scene, the occluders -- with a colour (``rgba``), ``specular``, ``shininess``,
  ``reflectance`` and one of the procedural textures of :data:`TEXTURES` (MuJoCo builtin
  ``flat``/``checker``/``gradient`` cube textures in grey, tinted by the material's colour) or
  none;
* per image: the key light's direction and colour, a point fill light's position and colour,
  and the ambient (head) light's level.

The texture bank is the same in every model, so all objects share one rendering context.
"""

from __future__ import annotations

import json
from typing import Any

import mujoco
import numpy as np

from articulated_dataset.format.schema import MASK_FIRST_PART, MASK_OCCLUDER, MASK_SCENE
from articulated_dataset.generation.config import APPEARANCE_STREAM  # noqa: F401  (the stream's word, :func:`.config.appearance_rng`)

#: Procedural textures every ``--rgb`` model holds: (name, MuJoCo builtin, light grey, dark grey).
TEXTURES = (
    ("rgb_flat", "FLAT", 1.0, 1.0),
    ("rgb_checker", "CHECKER", 1.0, 0.45),
    ("rgb_checker_fine", "CHECKER", 0.9, 0.6),
    ("rgb_gradient", "GRADIENT", 1.0, 0.4),
)
TEXTURE_SIZE_PX = {"rgb_checker_fine": 256}  # the others: 64 (cells of 32 px: a coarse checker)
#: Every range of the randomisation (uniform), recorded in every ``--rgb`` shard (attribute
#: ``appearance``).  Floors keep object pixels non-black: ambient x colour x texture >= 0.2 x
#: 0.2 x 0.4 of full scale (>= 4 of 255).
APPEARANCE_TABLE: dict[str, Any] = {
    "material_rgb": (0.2, 1.0),  # per channel
    "specular": (0.0, 0.8),
    "shininess": (0.0, 1.0),
    "reflectance": (0.0, 0.2),
    "texture_probability": 0.6,  # else the plain material colour; textures chosen uniformly
    "key_light_azimuth_deg": (-60.0, 60.0),  # direction it comes from, about the optical axis
    "key_light_elevation_deg": (15.0, 75.0),
    "key_light_intensity": (0.3, 0.8),
    "fill_light_pos_m": ((-0.5, 1.0), (-2.0, 2.0), (-0.5, 2.0)),  # x (forward), y (left), z (up), camera frame
    "fill_light_intensity": (0.0, 0.5),
    "light_rgb": (0.7, 1.0),  # per channel, times the intensity
    "ambient": (0.2, 0.4),  # grey level of the ambient (head) light
}
#: Side (px) of the key light's shadow map in ``--rgb`` models (MuJoCo's default, 4096, made a
#: software-rendered colour frame ~20x slower than its depth frame; 1024 is finer than any
#: image's pixels at the default 192 x 108).
SHADOW_SIZE_PX = 1024
#: Material slots: 0 body, 1 + j moving part j, then scene, then occluders.
FILL_LIGHT = "rgb_fill"
KEY_LIGHT = "key"


def appearance_record() -> str:
    """The shard attribute ``appearance``: textures and ranges (JSON)."""
    return json.dumps({"textures": [t[0] for t in TEXTURES], "ranges": APPEARANCE_TABLE}, sort_keys=True)


def n_material_slots(n_joints: int) -> int:
    """Number of material slots of a model with ``n_joints`` moving parts: body, one per part, scene, occluders."""
    return 1 + n_joints + 2


def with_appearance_assets(add_context, n_joints: int):
    """A spec hook adding the texture bank, the material slots and the fill light (after
    ``add_context``, if any), and setting the shadow map's size: the model compiles to the same
    geoms, bodies and depth."""
    def add(spec):
        if add_context is not None:
            add_context(spec)
        spec.visual.quality.shadowsize = SHADOW_SIZE_PX
        for name, builtin, light, dark in TEXTURES:
            size = TEXTURE_SIZE_PX.get(name, 64)
            spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_CUBE,
                             builtin=getattr(mujoco.mjtBuiltin, f"mjBUILTIN_{builtin}"),
                             rgb1=[light] * 3, rgb2=[dark] * 3, width=size, height=size)
        for k in range(n_material_slots(n_joints)):
            spec.add_material(name=f"rgb_material_{k}")
        spec.worldbody.add_light(name=FILL_LIGHT, pos=[0.0, 0.0, 1.0], type=int(mujoco.mjtLightType.mjLIGHT_POINT),
                                 castshadow=False)
    return add


def _slot_of_code(code: np.ndarray, n_joints: int) -> np.ndarray:
    slot = np.full(code.shape, -1, np.int64)
    slot[code == 1] = 0
    part = (code >= MASK_FIRST_PART) & (code < MASK_FIRST_PART + n_joints)
    slot[part] = code[part].astype(np.int64) - MASK_FIRST_PART + 1
    slot[code == MASK_SCENE] = 1 + n_joints
    slot[code == MASK_OCCLUDER] = 2 + n_joints
    return slot


class Appearance:
    """One compiled ``--rgb`` model's looks: :meth:`dress` draws its materials (once per
    model), :meth:`light` each image's lights."""

    def __init__(self, model: mujoco.MjModel, geom_part: np.ndarray, n_joints: int, rng: np.random.Generator):
        self.model, self.rng, self.J = model, rng, n_joints
        self.mat0 = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, "rgb_material_0")
        self.tex = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, t[0]) for t in TEXTURES]
        self.key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_LIGHT, KEY_LIGHT)
        self.fill = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_LIGHT, FILL_LIGHT)
        if min(self.mat0, self.key, self.fill, *self.tex) < 0:
            raise ValueError("the model was not compiled with with_appearance_assets")
        self.geom_slot = _slot_of_code(np.asarray(geom_part), n_joints)

    def dress(self) -> None:
        """Draw every material slot (in slot order: rgb, specular, shininess, reflectance,
        texture or none) and assign the slots to the geoms by mask code."""
        m, rng, t = self.model, self.rng, APPEARANCE_TABLE
        for k in range(n_material_slots(self.J)):
            mat = self.mat0 + k
            m.mat_rgba[mat] = (*rng.uniform(*t["material_rgb"], size=3), 1.0)  # type: ignore[call-overload]  # mypy: *Any and size=
            m.mat_specular[mat] = rng.uniform(*t["specular"])
            m.mat_shininess[mat] = rng.uniform(*t["shininess"])
            m.mat_reflectance[mat] = rng.uniform(*t["reflectance"])
            textured = rng.random() < t["texture_probability"]
            tex = self.tex[int(rng.integers(len(self.tex)))]
            m.mat_texid[mat] = -1
            m.mat_texid[mat, mujoco.mjtTextureRole.mjTEXROLE_RGB] = tex if textured else -1
        on = self.geom_slot >= 0
        m.geom_matid[on] = self.mat0 + self.geom_slot[on]
        m.geom_rgba[on] = (0.5, 0.5, 0.5, 1.0)  # MuJoCo's default: the material's colour shows

    def light(self, data: mujoco.MjData) -> None:
        """Draw this image's lights (key direction, intensity, colour; fill position,
        intensity, colour; ambient) and update their world poses in ``data``."""
        m, rng, t = self.model, self.rng, APPEARANCE_TABLE
        az = np.deg2rad(rng.uniform(*t["key_light_azimuth_deg"]))
        el = np.deg2rad(rng.uniform(*t["key_light_elevation_deg"]))
        # It shines forward (+x) from above the camera, turned by the azimuth about +z.
        m.light_dir[self.key] = (np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el))
        m.light_diffuse[self.key] = rng.uniform(*t["light_rgb"], size=3) * rng.uniform(*t["key_light_intensity"])  # type: ignore[call-overload]  # mypy: *Any and size=
        m.light_pos[self.fill] = [rng.uniform(lo, hi) for lo, hi in t["fill_light_pos_m"]]
        m.light_diffuse[self.fill] = rng.uniform(*t["light_rgb"], size=3) * rng.uniform(*t["fill_light_intensity"])  # type: ignore[call-overload]  # mypy: *Any and size=
        ambient = rng.uniform(*t["ambient"])
        m.vis.headlight.ambient = (ambient,) * 3
        m.vis.headlight.diffuse = (0.0, 0.0, 0.0)
        m.vis.headlight.specular = (0.0, 0.0, 0.0)
        mujoco.mj_camlight(m, data)
