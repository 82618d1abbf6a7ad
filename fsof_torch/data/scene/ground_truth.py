"""Ground truth of a pair from the 3D geometry: flow (the hit points moved rigidly and projected
into frame t+1), validity (in view and not occluded at t+1), the instantaneous flow in px/s, and
the camera's pose over the road and its rigid motion between the two frames."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from ...geometry.camera import mounting_matrix
from .config import SKY
from .motion import rot_y
from .objects import SceneObject
from .raycast import Hits
from .world import Scene


#: A point whose projection at t+1 lies within this many px of its own pixel counts as inside the
#: image (``valid``), also where rounding puts it outside [0, W - 1] × [0, H - 1]: above the rounding
#: of the projection (a static point seen by a camera standing still moves by up to 5e-13 px in
#: float64 and 2.4e-4 px in float32 at 375×1242), far below the 1/64 px steps of a KITTI flow PNG.
STILL = 1e-3


def _apply(M: list[list[float]], x: Tensor, y: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """M (3×3 Python floats) applied to vectors given by their components."""
    return tuple(M[r][0] * x + M[r][1] * y + M[r][2] * z for r in range(3))


def _moving_object_tables(scene: Scene, objects: list[SceneObject], k: int, dtype: torch.dtype):
    """Per object (rows) the rigid motion from frame k to k+1, p' = M p + b (world), and the
    instantaneous velocity field ṗ = v + Ω (p - c) at frame k; static objects get the identity."""
    N = len(objects)
    M = torch.eye(3, dtype=torch.float64).repeat(N, 1, 1)
    b = torch.zeros(N, 3, dtype=torch.float64)
    V = torch.zeros(N, 3, dtype=torch.float64)
    Om = torch.zeros(N, 3, 3, dtype=torch.float64)
    C = torch.zeros(N, 3, dtype=torch.float64)
    J = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    moving = torch.zeros(N, dtype=torch.bool)
    for i, o in enumerate(objects):
        if o.vs == 0.0:
            continue
        moving[i] = True
        c0, p0 = scene.object_pose(o, k)
        c1, p1 = scene.object_pose(o, k + 1)
        R0 = torch.tensor(rot_y(p0), dtype=torch.float64)
        R1 = torch.tensor(rot_y(p1), dtype=torch.float64)
        # p_local = R0 (p - c0) = R1 (p' - c1)
        M[i] = R1.T @ R0
        b[i] = torch.tensor(c1, dtype=torch.float64) - M[i] @ torch.tensor(c0, dtype=torch.float64)
        # the reference point on the lane line moves along the arc; the body turns about it
        s = o.s0 + o.vs * k * scene.motion.dt
        x, z, psi_s = scene.road.to_world(o.e, s)
        speed = o.vs * (1 - scene.road.kappa * o.e)
        yaw_rate = o.vs * scene.road.kappa
        climb = -scene.grade.slope_at(s) * o.vs if scene.grade.active else 0.0  # y is down
        V[i] = torch.tensor([speed * math.sin(psi_s), climb, speed * math.cos(psi_s)], dtype=torch.float64)
        # p = c + R_ψᵀ l  =>  ṗ = ċ - ψ̇ J (p - c)
        Om[i] = -yaw_rate * J
        C[i] = torch.tensor([x, 0.0, z], dtype=torch.float64)
    return moving, M.to(dtype), b.to(dtype), V.to(dtype), Om.to(dtype), C.to(dtype)


def ground_truth(scene: Scene, k: int, hits: Hits, next_inv_depth: Tensor) -> dict[str, Tensor]:
    """Flow, validity and px/s flow of pixel-centre hits at frame k (grids (H, W))."""
    dtype = scene.dtype
    H, W = hits.t.shape
    sky = hits.label == SKY
    t = torch.where(sky, 0.0, hits.t)
    ox, oy, oz = hits.origin
    # world points at frame k (sky: the ray direction, a point at infinity)
    Px = torch.where(sky, hits.dx, ox + t * hits.dx)
    Py = torch.where(sky, hits.dy, oy + t * hits.dy)
    Pz = torch.where(sky, hits.dz, oz + t * hits.dz)
    moving, M, b, V, Om, C = _moving_object_tables(scene, hits.objects, k, dtype)
    idx = None
    if bool(moving.any()):
        on_moving = (hits.obj >= 0) & moving[hits.obj.clamp_min(0)]
        if bool(on_moving.any()):
            idx = on_moving.nonzero(as_tuple=True)
            oid = hits.obj[idx]
            P_sel = torch.stack([Px[idx], Py[idx], Pz[idx]], dim=-1)
            P1_sel = (M[oid] @ P_sel.unsqueeze(-1)).squeeze(-1) + b[oid]
            Pdot_sel = V[oid] + (Om[oid] @ (P_sel - C[oid]).unsqueeze(-1)).squeeze(-1)
    P1x, P1y, P1z = Px, Py, Pz
    if idx is not None:
        P1x, P1y, P1z = (q.index_put(idx, P1_sel[:, r]) for r, q in enumerate((Px, Py, Pz)))
    A1, c1 = scene.world_to_camera(k + 1)
    # camera of t+1; directions at infinity are rotated only
    not_sky = (~sky).to(dtype)
    X, Y, Z = _apply(A1, P1x - c1[0] * not_sky, P1y - c1[1] * not_sky, P1z - c1[2] * not_sky)
    Kt = scene.K
    front = Z > 1e-6
    Zs = torch.where(front, Z, 1.0)
    u1 = (Kt[0][0] * X + Kt[0][1] * Y) / Zs + Kt[0][2]
    v1 = Kt[1][1] * Y / Zs + Kt[1][2]
    u = torch.arange(W, dtype=dtype).reshape(1, W)
    v = torch.arange(H, dtype=dtype).reshape(H, 1)
    flow = torch.stack([torch.where(front, u1 - u, 0.0), torch.where(front, v1 - v, 0.0)])
    # inside [0, W - 1] x [0, H - 1], or within STILL px of its own pixel: a border pixel whose point
    # stays put (a camera standing still) projects onto itself only up to rounding, either side
    stays = (flow[0].abs() <= STILL) & (flow[1].abs() <= STILL)
    inside = front & (((u1 >= 0) & (u1 <= W - 1) & (v1 >= 0) & (v1 <= H - 1)) | stays)
    # occlusion: inverse depth at t+1 interpolated at the projected position (exact on planes)
    grid = torch.stack([2 * u1 / max(W - 1, 1) - 1, 2 * v1 / max(H - 1, 1) - 1], dim=-1)
    grid = torch.where(inside.unsqueeze(-1), grid, 0.0)
    seen = F.grid_sample(next_inv_depth.reshape(1, 1, H, W), grid.unsqueeze(0), mode="bilinear",
                         padding_mode="border", align_corners=True)[0, 0]
    visible = (1.0 / Zs) * (1 + 2e-3) + 1e-9 >= seen
    valid = ~sky & inside & visible

    # px/s: p_cam = M p_v with p_v = R_ψ (P - c), M the camera's attitude relative to the heading
    # frame; ṗ_v = ω J p_v - R_ψ ċ + R_ψ ṗ_world, where R_ψ ċ = (0, 0, v_r) for the planar
    # motion alone; ṗ_cam = M ṗ_v + Ṁ p_v (Ṁ = 0 without body motion or grade)
    pose = scene.pose(k)
    c0 = pose.c
    _, _, psi = scene.ego_pose(k)
    Rpsi = rot_y(psi)
    mot = scene.motion
    omega = mot.yaw_rate
    pvx, pvy, pvz = _apply(Rpsi, Px - c0[0] * not_sky, Py - c0[1] * not_sky, Pz - c0[2] * not_sky)
    dvx = -omega * pvz
    dvy = torch.zeros_like(pvy)
    dvz = omega * pvx - mot.speed * not_sky
    if idx is not None:
        wx, wy, wz = _apply(Rpsi, Pdot_sel[:, 0], Pdot_sel[:, 1], Pdot_sel[:, 2])
        dvx, dvy, dvz = dvx.index_put(idx, dvx[idx] + wx), dvy.index_put(idx, wy), dvz.index_put(idx, dvz[idx] + wz)
    if scene.rides:
        mount_dot, centre_dot = scene.pose_rates(k)
        # the centre's velocity beyond the planar motion (height oscillation, riding the grade)
        planar = (mot.speed * math.sin(psi), 0.0, mot.speed * math.cos(psi))
        extra = [float(centre_dot[m]) - planar[m] for m in range(3)]
        ex, ey, ez = (sum(Rpsi[r][m] * extra[m] for m in range(3)) for r in range(3))
        dvx, dvy, dvz = dvx - ex * not_sky, dvy - ey * not_sky, dvz - ez * not_sky
    Xc, Yc, Zc = _apply(pose.mount, pvx, pvy, pvz)
    dXc, dYc, dZc = _apply(pose.mount, dvx, dvy, dvz)
    if scene.rides:
        mx, my, mz = _apply(mount_dot.tolist(), pvx, pvy, pvz)
        dXc, dYc, dZc = dXc + mx, dYc + my, dZc + mz
    okc = Zc > 1e-6
    Zc = torch.where(okc, Zc, 1.0)
    dx_ = (dXc * Zc - Xc * dZc) / (Zc * Zc)
    dy_ = (dYc * Zc - Yc * dZc) / (Zc * Zc)
    fu = torch.where(okc, Kt[0][0] * dx_ + Kt[0][1] * dy_, 0.0)
    fv = torch.where(okc, Kt[1][1] * dy_, 0.0)
    return {"flow": flow, "valid": valid.unsqueeze(0), "flow_velocity": torch.stack([fu, fv])}


def road_motion(scene: Scene, k: int) -> tuple[dict[str, float], dict[str, float]]:
    """The camera over the road at frame k and its rigid motion to frame k+1 (DESIGN.md §10).

    ``road_pose``: ``pitch``, ``roll`` (rad) of the camera relative to the road's tangent plane
    under the vehicle at k, and its ``height`` (m) over that plane. ``plane``: with
    R_c = R_roll(roll) R_pitch(pitch), the camera motion X' = R X + t (camera k -> camera k+1,
    from the two poses) written as R = R_c R_v R_cᵀ, t = -R_c R_v d, where
    R_v = R_roll(roll_change) R_pitch(pitch_change) R_yaw(yaw) and d = (x_d, y_d, z_d) is the
    camera's displacement in the road-aligned vehicle frame of k (x right, y down along the road
    normal, z forward); plus the ``road_pose`` values. Floats, radians and metres.
    """
    p0, p1 = scene.pose(k), scene.pose(k + 1)
    A0, A1 = (torch.tensor(p.A, dtype=torch.float64) for p in (p0, p1))
    c0, c1 = (torch.tensor(p.c, dtype=torch.float64) for p in (p0, p1))
    R = A1 @ A0.T
    t = A1 @ (c0 - c1)
    Rc = mounting_matrix(torch.tensor([p0.roll], dtype=torch.float64), torch.tensor([p0.pitch], dtype=torch.float64))[0]
    Rv = Rc.T @ R @ Rc
    d = -(Rv.T @ (Rc.T @ t))
    # R_v = R_roll(γ) R_pitch(α) R_yaw(φ): its last row is (cos α sin φ, -sin α, cos α cos φ), its
    # second column (sin γ cos α, cos γ cos α, -sin α)
    road_pose = {"pitch": p0.pitch, "roll": p0.roll, "height": p0.height}
    plane = {
        "pitch_change": math.atan2(-float(Rv[2, 1]), math.hypot(float(Rv[2, 0]), float(Rv[2, 2]))),
        "yaw": math.atan2(float(Rv[2, 0]), float(Rv[2, 2])),
        "roll_change": math.atan2(float(Rv[0, 1]), float(Rv[1, 1])),
        "x_d": float(d[0]), "y_d": float(d[1]), "z_d": float(d[2]),
        **road_pose,
    }
    return road_pose, plane
