"""Procedural driving scenes with exact ground truth, rendered by vectorised torch ray casting.

The scenes test the road-flow formula instead of repeating it: every ground-truth quantity comes
from the 3D geometry (ray / surface / box intersections, rigid motions, pinhole projection), never
from :func:`fsof_torch.flow_model.displacement_flow`.

Scene: a road (the plane y = h of the world frame; on a graded road the surface y = h - g(s))
with lane markings, raised pavements behind kerbs, building façades, parked and moving cars (a body
box and a cabin box each) and a sky at infinity. The road is straight, or an arc concentric with
the ego vehicle's path so that a turning car stays in the centre of its lane (the configuration
keeps the path's radius at least 8 m and more than half a lane width). Textures are multi-scale
value noise from a seeded generator, band-limited per pixel (octaves finer than the pixel
footprint fade out) so that frames warp onto each other and optical flow can track the road.

Frames (DESIGN.md §2): the world frame is level (x right, y down, z along the road at its start,
road at y = h under the vehicle at frame 0); on a level road without body motion it is the vehicle
frame of frame 0 (origin at the camera). A pose (c, ψ) maps world points into a local
frame as ``p_local = R_ψ (p_world - c)`` with ``R_ψ = [[cos ψ, 0, -sin ψ], [0, 1, 0],
[sin ψ, 0, cos ψ]]``; the ego vehicle, the buildings and the cars all use it. The camera sees
``p_cam = R_roll R_pitch p_vehicle`` (:class:`fsof_torch.camera.Camera`).

Beyond the paper (DESIGN.md §10): the body may oscillate over the road (the camera's pitch, roll
and height relative to the road at frame k follow slow sinusoids), and a straight road may have a
grade (its surface is y = h - g(s), a crest or a dip, with the ego vehicle riding on it). Then the
camera at frame k sees ``p_cam = R_roll(θ_k) R_pitch(β_k) R_ψ_k (p_world - c_k)`` with θ_k, β_k
the mounting plus the oscillation (plus the road's slope under the vehicle in β_k) and c_k at the
oscillating height over the road along its normal; the world is the level frame whose road at
s = 0 is y = h (:mod:`.world`). ``road_pose`` and ``plane`` give the exact pose over the road and
the rigid plane motion of each pair.

Ground truth per pair (frames t = index, t+1):

* ``flow``: each pixel centre's ray at t meets a surface at a 3D point; the point moves with its
  object (static world, or a moving car's rigid motion), is expressed in the camera of t+1 and
  projected; flow = projection − pixel. Sky pixels get the flow of a direction at infinity
  (rotation only) and are not valid.
* ``valid``: a 3D point exists, lies in front of the camera at t+1, projects inside
  [0, W−1] × [0, H−1] (or within 1e-3 px of its own pixel, :data:`.ground_truth.STILL`: a border
  pixel of a camera standing still stays valid whatever the rounding) and is not occluded there: its inverse depth is compared with the inverse
  depth render of frame t+1 interpolated bilinearly at the projected position (bilinear
  interpolation of inverse depth is exact on planes; at depth edges it errs toward "occluded").
* ``flow_velocity`` (px/s): the analytic time derivative of each point's projection under the
  instantaneous ego motion (forward rate v_r, lateral rate 0, yaw rate v_r tan δ_f / l; with
  body motion or a grade, the rates of the camera's attitude and height as well) and, for moving
  cars, the car's own velocity.
* ``depth``: camera z in metres (0 on the sky); ``labels``: see :data:`LABELS`; ``road``: road
  or marking pixels, the freespace (on the road surface: the plane y = h, or y = h - g(s) on a
  crest or a dip).
* ``road_pose``, ``plane``: the camera over the road's tangent plane at t and its rigid motion
  to t+1 (:func:`.ground_truth.road_motion`).

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
