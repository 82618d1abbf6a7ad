"""Procedural driving scenes with exact ground truth, rendered by vectorised torch ray casting.

The scenes test the road-flow formula instead of repeating it: every ground-truth quantity comes
from the 3D geometry (ray / plane / box intersections, rigid motions, pinhole projection), never
from :func:`fsof_torch.flow_model.displacement_flow`.

Scene: a road (the plane y = h of the vehicle frame) with lane markings, raised pavements behind
kerbs, building façades, parked and moving cars (a body box and a cabin box each) and a sky at
infinity. The road is straight, or an arc whose curvature matches the ego vehicle's steering so
that a turning car stays in its lane. Textures are multi-scale value noise from a seeded
generator, band-limited per pixel (octaves finer than the pixel footprint fade out) so that
frames warp onto each other and optical flow can track the road.

Frames (DESIGN.md §2): the world frame is the vehicle frame of frame 0 (x right, y down,
z forward, origin at the camera, road at y = h). A pose (c, ψ) maps world points into a local
frame as ``p_local = R_ψ (p_world - c)`` with ``R_ψ = [[cos ψ, 0, -sin ψ], [0, 1, 0],
[sin ψ, 0, cos ψ]]``; the ego vehicle, the buildings and the cars all use it. The camera sees
``p_cam = R_roll R_pitch p_vehicle`` (:class:`fsof_torch.camera.Camera`).

Ground truth per pair (frames t = index, t+1):

* ``flow``: each pixel centre's ray at t meets a surface at a 3D point; the point moves with its
  object (static world, or a moving car's rigid motion), is expressed in the camera of t+1 and
  projected; flow = projection − pixel. Sky pixels get the flow of a direction at infinity
  (rotation only) and are not valid.
* ``valid``: a 3D point exists, lies in front of the camera at t+1, projects inside
  [0, W−1] × [0, H−1] and is not occluded there: its inverse depth is compared with the inverse
  depth render of frame t+1 interpolated bilinearly at the projected position (bilinear
  interpolation of inverse depth is exact on planes; at depth edges it errs toward "occluded").
* ``flow_velocity`` (px/s): the analytic time derivative of each point's projection under the
  instantaneous ego motion (forward rate v_r, lateral rate 0, yaw rate v_r tan δ_f / l) and, for
  moving cars, the car's own velocity.
* ``depth``: camera z in metres (0 on the sky); ``labels``: see :data:`LABELS`; ``road``: road
  or marking pixels (the plane y = h, the freespace).

The package, one idea per module: :mod:`.config` (labels, :class:`SceneConfig`, presets),
:mod:`.motion` (the ego vehicle's motion), :mod:`.road` (road coordinates), :mod:`.objects`
(buildings and cars), :mod:`.world` (a configured scene and its camera poses), :mod:`.raycast`,
:mod:`.shading` (textures, light, sensor noise), :mod:`.ground_truth` and :mod:`.render`.

Example:
    >>> from fsof_torch.scene import render_pair
    >>> pair = render_pair("default", 0, size=(96, 320))
    >>> pair["image1"].shape, pair["flow"].shape, pair["road"].dtype
    (torch.Size([3, 96, 320]), torch.Size([2, 96, 320]), torch.bool)
"""

from .config import KITTI_K, KITTI_SIZE, LABEL_COLORS, LABELS, PRESETS, SENSOR_NOISE, SceneConfig, scene_config
from .render import collate, render_pair, render_sequence

__all__ = [
    "LABELS",
    "LABEL_COLORS",
    "PRESETS",
    "SENSOR_NOISE",
    "KITTI_K",
    "KITTI_SIZE",
    "SceneConfig",
    "scene_config",
    "render_pair",
    "render_sequence",
    "collate",
]
