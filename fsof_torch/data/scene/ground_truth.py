"""Ground truth of a pair from the 3D geometry: flow (the hit points moved rigidly and projected
into frame t+1), validity (in view and not occluded at t+1) and the instantaneous flow in px/s."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from .config import SKY
from .motion import rot_y
from .objects import SceneObject
from .raycast import Hits
from .world import Scene


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
        x, z, psi_s = scene.road.to_world(o.e, o.s0 + o.vs * k * scene.motion.dt)
        speed = o.vs * (1 - scene.road.kappa * o.e)
        yaw_rate = o.vs * scene.road.kappa
        V[i] = torch.tensor([speed * math.sin(psi_s), 0.0, speed * math.cos(psi_s)], dtype=torch.float64)
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
    ox, oz = hits.origin[0], hits.origin[2]
    # world points at frame k (sky: the ray direction, a point at infinity)
    Px = torch.where(sky, hits.dx, ox + t * hits.dx)
    Py = torch.where(sky, hits.dy, t * hits.dy)
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
    inside = front & (u1 >= 0) & (u1 <= W - 1) & (v1 >= 0) & (v1 <= H - 1)
    # occlusion: inverse depth at t+1 interpolated at the projected position (exact on planes)
    grid = torch.stack([2 * u1 / max(W - 1, 1) - 1, 2 * v1 / max(H - 1, 1) - 1], dim=-1)
    grid = torch.where(inside.unsqueeze(-1), grid, 0.0)
    seen = F.grid_sample(next_inv_depth.reshape(1, 1, H, W), grid.unsqueeze(0), mode="bilinear",
                         padding_mode="border", align_corners=True)[0, 0]
    visible = (1.0 / Zs) * (1 + 2e-3) + 1e-9 >= seen
    valid = ~sky & inside & visible

    # px/s: p_v = R_ψ (P - c); ṗ_v = ω J p_v - (0, 0, v_r) + R_ψ ṗ_world; p_cam = R_c p_v
    A0, c0 = scene.world_to_camera(k)
    _, _, psi = scene.ego_pose(k)
    Rpsi = rot_y(psi)
    mot = scene.motion
    omega = mot.speed * math.tan(mot.steering) / mot.wheelbase
    pvx, pvy, pvz = _apply(Rpsi, Px - c0[0] * not_sky, Py - c0[1] * not_sky, Pz - c0[2] * not_sky)
    dvx = -omega * pvz
    dvy = torch.zeros_like(pvy)
    dvz = omega * pvx - mot.speed * not_sky
    if idx is not None:
        wx, wy, wz = _apply(Rpsi, Pdot_sel[:, 0], Pdot_sel[:, 1], Pdot_sel[:, 2])
        dvx, dvy, dvz = dvx.index_put(idx, dvx[idx] + wx), dvy.index_put(idx, wy), dvz.index_put(idx, dvz[idx] + wz)
    Rc = scene.Rc
    Xc, Yc, Zc = _apply(Rc, pvx, pvy, pvz)
    dXc, dYc, dZc = _apply(Rc, dvx, dvy, dvz)
    okc = Zc > 1e-6
    Zc = torch.where(okc, Zc, 1.0)
    dx_ = (dXc * Zc - Xc * dZc) / (Zc * Zc)
    dy_ = (dYc * Zc - Yc * dZc) / (Zc * Zc)
    fu = torch.where(okc, Kt[0][0] * dx_ + Kt[0][1] * dy_, 0.0)
    fv = torch.where(okc, Kt[1][1] * dy_, 0.0)
    return {"flow": flow, "valid": valid.unsqueeze(0), "flow_velocity": torch.stack([fu, fv])}

