"""Ray casting: the nearest surface (road, kerb, pavement, box, or the sky) along each sample's
viewing ray, closed-form intersections in the scene's dtype (on a graded road the ground's in
float64: :meth:`fsof_torch.data.scene.road.Grade.first_hit`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .config import BUILDING, CAR, KERB, PAVEMENT, ROAD, SKY
from .objects import BUILDING_BOX
from .world import Scene


def sample_grid(size: tuple[int, int], ss: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Sample coordinates u (W ss,) and v (H ss,) in pixels (pixel centres when ss is odd or 1)."""
    H, W = size
    u = (torch.arange(W * ss, dtype=torch.float64) + 0.5) / ss - 0.5
    v = (torch.arange(H * ss, dtype=torch.float64) + 0.5) / ss - 0.5
    return u.to(dtype), v.to(dtype)


class Hits:
    """Ray-cast results on a (Hs, Ws) grid of samples."""

    def __init__(self, **kw: Tensor) -> None:
        self.__dict__.update(kw)


def _box_slab(o_l: list[float], d_l: list[Tensor], half: tuple) -> tuple[Tensor, Tensor]:
    """Slab test of rays o_l + t d_l against the box |p_a| <= half_a: (t_near, t_far)."""
    t_near = t_far = None
    for a_ in range(3):
        da = d_l[a_]
        inv = 1.0 / torch.where(da.abs() > 1e-12, da, torch.full_like(da, 1e-12))
        ta = (-half[a_] - o_l[a_]) * inv
        tb = (half[a_] - o_l[a_]) * inv
        lo, hi = torch.minimum(ta, tb), torch.maximum(ta, tb)
        t_near = lo if t_near is None else torch.maximum(t_near, lo)
        t_far = hi if t_far is None else torch.minimum(t_far, hi)
    return t_near, t_far


def _ground(scene: Scene, origin: list[float], dx: Tensor, dy: Tensor, dz: Tensor) -> tuple[Tensor, Tensor]:
    """Ray parameter and label of the first hit with the road, the kerb faces and the raised
    pavement (inf and sky where a ray goes up)."""
    if scene.grade.active:
        return _ground_on_grade(scene, origin, dx, dy, dz)
    ox, oy, oz = origin
    h, kh = scene.h, scene.cfg.kerb_height
    road = scene.road
    w_road = scene.cfg.lane_width + scene.cfg.parking_width
    down = dy > 1e-9
    dy_safe = torch.where(down, dy, torch.ones_like(dy))
    t_road = (h - oy) / dy_safe
    e_road = road.lateral(ox + t_road * dx, oz + t_road * dz)
    t_pave = (h - kh - oy) / dy_safe
    e_pave = road.lateral(ox + t_pave * dx, oz + t_pave * dz)
    # the raised pavement is met first: a ray over it at kerb height hits its top
    on_pave = down & (e_pave.abs() >= w_road)
    on_road = down & ~on_pave & (e_road.abs() < w_road)
    kerb = down & ~on_pave & ~on_road
    t = torch.where(on_pave, t_pave, torch.where(on_road, t_road, float("inf")))
    label = torch.where(on_road, ROAD, torch.where(on_pave, PAVEMENT, SKY))
    if bool(kerb.any()):
        idx = kerb.nonzero(as_tuple=True)
        side = torch.sign(e_road[idx])
        tk = road.boundary_hit(side * w_road, ox, oz, dx[idx], dz[idx], t_pave[idx], t_road[idx])
        t = t.index_put(idx, tk)
        label = label.index_put(idx, torch.full_like(tk, KERB, dtype=torch.int64))
    return t, label


def _ground_on_grade(scene: Scene, origin: list[float], dx: Tensor, dy: Tensor, dz: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`_ground` on a straight road with a grade (road y = h - g(z), pavement kh higher),
    in float64. A ray meets the pavement top if it reaches the pavement's level over the
    pavement; else the road if it reaches the road's level over the road; else the kerb face
    toward which it moves, if it crosses that face while between the two levels; else nothing
    (the lateral offset is linear along a ray, and each level is met first where the ray goes
    below it)."""
    ox, oy, oz = origin
    dtype = dy.dtype
    dx, dy, dz = dx.double(), dy.double(), dz.double()
    h, kh = scene.h, scene.cfg.kerb_height
    road, grade = scene.road, scene.grade
    w_road = scene.cfg.lane_width + scene.cfg.parking_width
    t_road = grade.first_hit(oy, oz, dy, dz, h)
    t_pave = grade.first_hit(oy, oz, dy, dz, h - kh)

    def lateral(t: Tensor) -> Tensor:  # on a straight road e = x + e0
        return road.e0 + ox + torch.where(torch.isfinite(t), t, 0.0) * dx

    on_pave = torch.isfinite(t_pave) & (lateral(t_pave).abs() >= w_road)
    on_road = ~on_pave & torch.isfinite(t_road) & (lateral(t_road).abs() < w_road)
    # the kerb line x = ±w_road - e0 on the side the ray moves toward
    moving = dx != 0
    t_kerb = (torch.sign(dx) * w_road - road.e0 - ox) / torch.where(moving, dx, 1.0)
    t_kerb = torch.where(moving & torch.isfinite(t_pave), t_kerb, math.inf)
    below_pave = oy + t_kerb * dy >= h - kh - grade.elevation(oz + t_kerb * dz)
    # (t_kerb = inf: a ray that never reaches the pavement's level, such as one over a road that falls
    # away faster than it descends, or one along the kerb line, meets no kerb face)
    kerb = torch.isfinite(t_kerb) & ~on_pave & ~on_road & (t_kerb >= t_pave) & (t_kerb <= t_road) & below_pave
    t = torch.where(on_pave, t_pave, torch.where(on_road, t_road, torch.where(kerb, t_kerb, math.inf)))
    label = torch.where(on_road, ROAD, torch.where(on_pave, PAVEMENT, torch.where(kerb, KERB, SKY)))
    return t.to(dtype), label


def cast_rays(scene: Scene, k: int, u: Tensor, v: Tensor, *, grid: bool = True, details: bool = True) -> Hits:
    """Cast the rays of samples at frame k; nearest surface per ray.

    ``grid=True``: u (Ws,) and v (Hs,) are the axes of a (Hs, Ws) sample grid (objects are tested
    only on the grid rectangle their projection covers); ``grid=False``: u, v (N,) list N rays,
    sorted by v (objects are tested only on the run of rays within their rows).
    The ray direction has camera z = 1, so the ray parameter t is the camera depth.
    """
    dtype = scene.dtype
    A, c = scene.world_to_camera(k)
    Ki = scene.K_inv
    if grid:
        Hs, Ws = v.shape[0], u.shape[0]
        shape = (Hs, Ws)
        ug, vg = u.reshape(1, Ws), v.reshape(Hs, 1)
    else:
        shape = tuple(u.shape)
        ug, vg = u, v
    # camera direction (K⁻¹ p̃), then world direction Aᵀ d_cam (rank-1 grids in grid mode)
    dcx = Ki[0][0] * ug + Ki[0][1] * vg + Ki[0][2]
    dcy = Ki[1][1] * vg + Ki[1][2]
    dx, dy, dz = ((A[0][j] * dcx + A[1][j] * dcy + A[2][j]).expand(shape) for j in range(3))
    ox, oy, oz = c

    if grid:
        # rows entirely above the horizon see no level ground: skip them (a graded road may
        # rise above the horizon)
        rows = torch.ones(Hs, dtype=torch.bool) if scene.grade.active else (dy > 1e-9).any(dim=1)
        r0 = int(rows.to(torch.int8).argmax()) if bool(rows.any()) else Hs
        t = torch.full(shape, float("inf"), dtype=dtype)
        label = torch.full(shape, SKY, dtype=torch.int64)
        if r0 < Hs:
            t[r0:], label[r0:] = _ground(scene, c, dx[r0:], dy[r0:], dz[r0:])
    else:
        t, label = _ground(scene, c, dx, dy, dz)
    obj = torch.full(shape, -1, dtype=torch.int64)
    objects = scene.objects(k)
    if objects:
        centres, psis, boxes = _screen_boxes(scene, objects, k, A, c)
    if grid:
        step_u = (u[1] - u[0]).item() if Ws > 1 else 1.0
        step_v = (v[1] - v[0]).item() if Hs > 1 else 1.0
        u0, v0 = u[0].item(), v[0].item()
    for i, o in enumerate(objects):
        box = boxes[i]
        if box == "behind":
            continue
        if grid:
            j0 = max(int(math.floor((box[0] - u0) / step_u)), 0)
            j1 = min(int(math.ceil((box[1] - u0) / step_u)) + 1, Ws)
            i0 = max(int(math.floor((box[2] - v0) / step_v)), 0)
            i1 = min(int(math.ceil((box[3] - v0) / step_v)) + 1, Hs)
            if j0 >= j1 or i0 >= i1:
                continue
            sel = (slice(i0, i1), slice(j0, j1))
        else:
            # rays come sorted by v: the object's rows are one contiguous run
            lo = int(torch.searchsorted(v, torch.tensor(box[2], dtype=v.dtype)))
            hi = int(torch.searchsorted(v, torch.tensor(box[3], dtype=v.dtype), right=True))
            if lo >= hi:
                continue
            inside = (u[lo:hi] >= box[0]) & (u[lo:hi] <= box[1])
            sel = (inside.nonzero(as_tuple=True)[0] + lo,)
            if sel[0].numel() == 0:
                continue
        ddx, ddy, ddz = dx[sel], dy[sel], dz[sel]
        centre, (cs, sn) = centres[i], psis[i]
        rel = (ox - centre[0], oy - centre[1], oz - centre[2])
        o_l = [cs * rel[0] - sn * rel[2], rel[1], sn * rel[0] + cs * rel[2]]
        d_l = [cs * ddx - sn * ddz, ddy, sn * ddx + cs * ddz]
        t_near, t_far = _box_slab(o_l, d_l, o.half)
        t_sel = t[sel]
        hit = (t_near <= t_far) & (t_near > 1e-6) & (t_near < t_sel)
        t[sel] = torch.where(hit, t_near, t_sel)
        obj[sel] = torch.where(hit, i, obj[sel])
    out = Hits(t=t, label=label, obj=obj, dx=dx, dy=dy, dz=dz, objects=objects, origin=c, k=k)
    if objects:
        kinds = torch.tensor([BUILDING if o.kind == BUILDING_BOX else CAR for o in objects] + [0])
        out.label = torch.where(obj >= 0, kinds[obj], label)
    if details:
        # hit points in the hit object's own frame, and the face they lie on
        idx = (obj >= 0).nonzero(as_tuple=True)
        out.box_idx = idx
        if idx[0].numel():
            oid = obj[idx]
            tt = t[idx]
            table = torch.tensor([[*centres[i], *psis[i], *o.half] for i, o in enumerate(objects)], dtype=dtype)[oid]
            rx = ox + tt * dx[idx] - table[:, 0]
            ry = oy + tt * dy[idx] - table[:, 1]
            rz = oz + tt * dz[idx] - table[:, 2]
            cs, sn = table[:, 3], table[:, 4]
            local = torch.stack([cs * rx - sn * rz, ry, sn * rx + cs * rz], dim=1)
            out.box_local = local
            out.box_face = (local.abs() / table[:, 5:8]).argmax(dim=1)
    return out


def _screen_boxes(scene: Scene, objects: list, k: int, A: list, c: list):
    """Per object: centre (3 floats), (cos ψ, sin ψ), and the pixel rectangle (u_min, u_max,
    v_min, v_max) that bounds its part in front of the camera, or ``"behind"``."""
    poses = [scene.object_pose(o, k) for o in objects]
    centre = torch.tensor([p[0] for p in poses], dtype=torch.float64)
    psi = torch.tensor([p[1] for p in poses], dtype=torch.float64)
    half = torch.tensor([o.half for o in objects], dtype=torch.float64)
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)
    loc = signs.unsqueeze(0) * half.unsqueeze(1)  # (N, 8, 3)
    cs, sn = torch.cos(psi).unsqueeze(1), torch.sin(psi).unsqueeze(1)
    # world = centre + R_ψᵀ loc
    world = torch.stack([centre[:, 0:1] + cs * loc[..., 0] + sn * loc[..., 2],
                         centre[:, 1:2] + loc[..., 1],
                         centre[:, 2:3] - sn * loc[..., 0] + cs * loc[..., 2]], dim=-1)
    cam = (world - torch.tensor(c, dtype=torch.float64)) @ torch.tensor(A, dtype=torch.float64).T
    Kt = torch.tensor(scene.K, dtype=torch.float64)
    near = 0.05
    # a box straddling the camera plane is bounded by its corners in front and by the points where
    # its 12 edges cross the near plane
    ends = torch.tensor([(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1])
    P1, P2 = cam[:, ends[:, 0]], cam[:, ends[:, 1]]
    Z1, Z2 = P1[..., 2:], P2[..., 2:]
    crosses = ((Z1 - near) * (Z2 - near) < 0)[..., 0]
    w = ((near - Z1) / torch.where(Z2 != Z1, Z2 - Z1, 1.0)).clamp(0, 1)
    points = torch.cat([cam, P1 + w * (P2 - P1)], dim=1)  # (N, 20, 3)
    use = torch.cat([cam[..., 2] > near, crosses], dim=1)
    Z = points[..., 2].clamp_min(near)
    us = (Kt[0, 0] * points[..., 0] + Kt[0, 1] * points[..., 1]) / Z + Kt[0, 2]
    vs = Kt[1, 1] * points[..., 1] / Z + Kt[1, 2]
    big = torch.tensor(1e9, dtype=torch.float64)
    rect = torch.stack([torch.where(use, us, big).amin(1) - 1, torch.where(use, us, -big).amax(1) + 1,
                        torch.where(use, vs, big).amin(1) - 1, torch.where(use, vs, -big).amax(1) + 1], dim=1)
    rect = rect.clamp(-1e6, 1e6).tolist()
    seen = use.any(dim=1).tolist()
    boxes = [tuple(rect[i]) if seen[i] else "behind" for i in range(len(objects))]
    cossin = list(zip(cs[:, 0].tolist(), sn[:, 0].tolist()))
    return [p[0] for p in poses], cossin, boxes

