"""Third-party articulated objects from URDF files (e.g. PartNet-Mobility).

``artdata generate --urdf FILE`` renders a user-supplied URDF with the dataset's camera,
pose and configuration sampling and label definitions.  The URDF is turned into a
*processed* URDF that the pipeline treats like any class template:

* the file is data, never code: it is parsed as plain XML (lxml with entity expansion,
  network access and DTDs off, no XInclude; a DOCTYPE is refused) and read into yourdfpy's
  structures; it never goes through xacro (only our own ``*.xacro`` templates do), and link
  and joint names must be plain identifiers (:data:`.parse.URDF_NAME_CHARS`);
* mesh paths are resolved with yourdfpy relative to the URDF (``package://`` prefixes are
  tried relative to the URDF's folder and its parents) and must lie inside the *mesh root*:
  the URDF's folder, or the folder the user names (``--mesh-root``);
* each link's geometry is its ``<visual>`` elements (its ``<collision>`` elements if it
  has no visual).  Meshes are loaded with trimesh, scaled, placed by their ``<origin>`` and
  merged into one binary STL per link (MuJoCo reads STL; a flat mesh gets a
  :data:`.process.FLAT_MESH_THICKNESS_M` thickness because MuJoCo needs a 3-D convex hull), with
  every triangle made double-sided (MuJoCo culls back faces; see :func:`.process.double_sided`);
  primitive boxes, cylinders and spheres are kept as they are;
* the joints to articulate (``--joints``, default: every revolute and prismatic joint with
  a finite, non-empty range, in file order: the parts that open; ``continuous`` joints such
  as knobs are articulated only when named) keep their type; every other joint is frozen
  (``fixed``) at its URDF zero, the pose the meshes are modelled in;
* ``--scale s`` multiplies every length (mesh vertices, primitive sizes, joint and element
  origins, prismatic limits) by ``s``, for files in other units (PartNet-Mobility's are
  normalised); labels are read from the scaled model, so they follow;
* joint coordinates are re-parametrised so that q = 0 is closed and positive q opens: the
  closed pose is the limit nearer the URDF zero (the modelled pose; the lower limit on a
  tie), limits ``[lo, hi]`` become ``[0, hi - lo]`` with the joint origin turned / shifted to
  that limit along the axis, and the axis flipped where the closed limit is ``hi``
  (:func:`.ranges.reparametrize_range`).  Continuous joints use the built-in revolute range
  [0, pi/2] rad;
* ``--scale auto:CLASS`` picks the scale that gives the body a standard size of a built-in
  class (:func:`.build.auto_scale`);
* each articulated link's protrusions (handles, knobs: the triangles outside its panel,
  :mod:`.panel`) become a second geom named ``*_handle``, which the labeller leaves out of
  the part's centre, as it does the built-in templates' handles;
* every link gets a fixed unit inertia: only kinematics is ever computed.

The processed files live in a content-addressed cache folder (:func:`.ranges.cache_root`), rebuilt
on demand by any process (spawned workers, Ray workers on other nodes) from the
*definition*: a small JSON-able dict (source path, joints, options, sha256 of the URDF and
its meshes) that :class:`articulated_dataset.generation.pipeline.GenerationConfig` carries in its
``third_party`` field.  A worker whose files differ from the driver's (changed file,
different copy on another node) stops with an error instead of writing different data.

Object frame and default pose table: the object frame is the URDF root link's frame; the
pose table places that frame (x, y, z, yaw), like the ``base`` link of the built-in
classes.  The default ranges keep the whole object (all links at q = 0) inside the image:
see :func:`.ranges.view_pose_ranges`.  Third-party classes are ``sided``: the chirality is read
from geometry like the built-in ones' (the side of the part centre the hinge line lies on).
Their geometry is fixed (the table's geometry ranges are the body's bounding box, for reference).

The modules: :mod:`.ranges` (pose ranges, joint re-parametrisation, class names, the cache
folder), :mod:`.panel` (a moving part's panel and protrusions), :mod:`.parse` (the URDF read and checked as data, the joint plans), :mod:`.process`
(the processed model in the cache) and :mod:`.build` (definition -> class, :func:`import_urdf`).
"""

from articulated_dataset.generation.urdf_import.build import UrdfObject, class_from_definition, import_urdf
from articulated_dataset.generation.urdf_import.ranges import CACHE_ENV

__all__ = ["CACHE_ENV", "UrdfObject", "class_from_definition", "import_urdf"]
