"""Galleries of labelled depth images (``artdata show``).

Each panel shows one stored image: depth colour-mapped per image (near = bright, far =
dark, :data:`.style.DEPTH_CMAP`, perceptually uniform) with pixels without a return in a neutral
light grey, lightly hill-shaded so surfaces read as 3-D; the labelled joint axes are drawn
on top, projected with the shard's intrinsics ``K`` (:func:`articulated_dataset.core.camera.project`):

* revolute joint: the hinge line through ``axis_origin`` along ``axis_direction``, over
  the moving part's visible extent along the axis (its mask pixels back-projected), with
  an arrowhead at the ``+axis_direction`` end (positive q opens, right-hand rule);
* prismatic joint: an arrow from ``axis_origin`` (the part's front face at q = 0) to
  ``axis_origin + q_max * axis_direction`` (the table's full travel), with a ring at the
  front face's current position ``axis_origin + q * axis_direction``;
* a filled dot at ``axis_origin``.

One colour per joint (:data:`.style.JOINT_COLOURS`), shared by the axis, the q read-out and the
moving part's outline.  ``rgb=True`` adds a shaded colour preview rendered from the same
scene, rebuilt from the manifest's generation config (body grey, parts tinted in their
joint's colour).

Real (ingested) splits: labels a capture lacks are NaN.  A revolute axis without part pixels
(binary masks) and without body extent (no geometry or object pose) spans the whole object's
visible extent along the axis; q not labelled reads "no label"; an image without axis labels
says so in its panel.

Figures are laid out with fixed sizes (no tight bounding box), so a gallery's pixel size is
:func:`.gallery.gallery_size_px` and every panel's position is known (:class:`.drawing.Panel`).  No text is
clipped: a split header or the legend too wide for the figure wraps onto more lines (the
figure grows by :data:`.style.HEADER_LINE_IN` / :data:`.style.LEGEND_LINE_IN` a line), a sample title or
joint name too wide for its panel is drawn smaller (:class:`.drawing.TextFitter` measures them).

The modules: :mod:`.style` (colours, sizes, depth colouring, axis extents), :mod:`.data` (the
split opened for drawing, sample choice, RGB preview), :mod:`.drawing` (one panel, captions,
header, legend) and :mod:`.gallery` (layout, figure checks, :func:`make_gallery`).  Importing this
package imports neither MuJoCo, OpenGL, torch nor jax (the RGB preview imports MuJoCo when used).
"""

from articulated_dataset.tools.viz.gallery import make_gallery

__all__ = ["make_gallery"]
