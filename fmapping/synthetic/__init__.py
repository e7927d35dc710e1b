"""Procedural textured indoor room with an exact RGB-D camera: the embedded default data.

Nothing is downloaded: a seed determines the whole scene (room, furniture, textures,
camera loop) and :func:`generate_scene` writes it in TUM layout with ground truth.

Conventions (on top of :mod:`fmapping.geometry`):

* World frame: metres, **z up**, floor at ``z = 0``, room centred on ``x = y = 0``.
* Surfaces are planar rectangles with integer *surface ids*: ``0`` floor, ``1``
  ceiling, ``2``/``3`` walls at x-min/x-max, ``4``/``5`` walls at y-min/y-max, and
  ``6 + 6 * b + f`` for face ``f`` of box ``b`` with ``f = 2 * axis + side``
  (axis of the box's local frame, side 0 = the ``-`` face, 1 = the ``+`` face).
  Boxes stand on the floor, so their bottom faces (``f = 4``) are never exposed.
* Colour is view-independent: a pure function of (surface id, 3-D point) given by
  :func:`surface_colour`, values in ``[0.05, 0.95]``. Rendered pixels are the
  average of ``supersample ** 2`` sub-pixel rays; depth is the camera-frame ``z``
  of the centre ray's hit (exact up to float rounding).
* Timestamps are ``i / 30`` s; depth PNGs hold ``round(depth * 5000)`` (0 invalid).

Varieties: ``"default"`` is the close-up, strongly textured room above (unchanged for
existing seeds). ``"wide"`` lets the seed also draw a :class:`Style`: texture scale and
contrast, near-uniform and striped surfaces, larger rooms and camera distances, thin
poles and panels, rotated furniture, and camera effects on the written colour frames
only (smooth per-frame gain and offset per channel, motion blur, sensor noise, JPEG).
Depth, poses, GT mesh and clouds stay exact; the drawn parameters go to
``scene.json["variety"]`` for reports (nothing in the pipeline reads them).
"""
from fmapping.synthetic.camera_effects import apply_camera_effects, exposure_curve, image_motion
from fmapping.synthetic.camera_path import (CLEARANCE_M, MAX_STEP_DEG, MAX_STEP_M, STEP_FILL, camera_clearance,
                                            make_trajectory, trajectory_steps)
from fmapping.synthetic.ground_truth import VISIBLE_TOL_M, gt_cloud, gt_mesh, visible_mask
from fmapping.synthetic.render import cast_rays, render_view
from fmapping.synthetic.scene import (VARIETIES, Box, LoopPath, Rect, Scene, Style, camera_for_size, draw_style,
                                      make_scene)
from fmapping.synthetic.texture import PATTERNS, Texture, surface_colour
from fmapping.synthetic.writers import DEPTH_FACTOR, FPS, generate_scene

__all__ = [
    "CLEARANCE_M", "DEPTH_FACTOR", "FPS", "MAX_STEP_DEG", "MAX_STEP_M", "PATTERNS", "STEP_FILL", "VARIETIES",
    "VISIBLE_TOL_M", "Box", "LoopPath", "Rect", "Scene", "Style", "Texture", "apply_camera_effects", "camera_clearance",
    "camera_for_size", "cast_rays", "draw_style", "exposure_curve", "generate_scene", "gt_cloud", "gt_mesh",
    "image_motion", "make_scene", "make_trajectory", "render_view", "surface_colour", "trajectory_steps",
    "visible_mask",
]
