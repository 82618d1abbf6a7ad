"""The scene's objects (building blocks, parked and moving cars), generated per 40 m block of
road from the scene seed, so that any stretch of road is reproducible on its own."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .config import SceneConfig, ego_speed, traffic_speed

BLOCK = 40.0  # metres of road per procedurally generated block of objects
BUILDING_BOX, CAR_BODY, CAR_CABIN = 0, 1, 2

@dataclass
class SceneObject:
    """A box of the scene (a building block, or a car's body or cabin), placed in road coordinates."""

    kind: int          # BUILDING_BOX, CAR_BODY, CAR_CABIN
    e: float           # lateral road coordinate of the reference point (m)
    s0: float          # arc length at frame 0 (m)
    vs: float          # arc-length speed (m/s), negative for oncoming cars
    half: tuple        # half extents (x, y, z) in the object's frame (m)
    y: float           # world y of the centre (m, down) on a level road
    offset: float      # shift of the centre along the object's z axis (m)
    reverse: bool      # facing against the road direction
    colour: tuple      # base RGB 0..255
    seed: int          # texture variation


def block_objects(cfg: SceneConfig, seed: int, block: int, road_kappa: float = 0.0) -> list[SceneObject]:
    """The objects generated for road block ``block`` (arc length [40 b, 40 (b + 1)) at frame 0)."""
    g = torch.Generator().manual_seed((seed * 1_000_003 + block * 7919 + 12345) % (2 ** 63))

    def uni(lo: float, hi: float) -> float:
        return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))

    def count(mean: float) -> int:
        return int(torch.poisson(torch.tensor(float(mean), dtype=torch.float64), generator=g)) if mean > 0 else 0

    h = cfg.height
    w_road = cfg.lane_width + cfg.parking_width
    s_start = block * BLOCK
    objs: list[SceneObject] = []
    if cfg.buildings:
        for side in (-1.0, 1.0):
            s = s_start + uni(0.0, 3.0)
            while s < s_start + BLOCK - 4.0:
                slot = min(uni(8.0, 22.0), s_start + BLOCK - s)
                length, depth, tall = slot, uni(8.0, 14.0), uni(6.0, 22.0)
                setback = uni(0.0, 1.5)
                if road_kappa * side > 0:
                    # inside a bend, about its centre: the façade (a straight box's side, tangent at
                    # radius r_face) stays clear of the centre, and its ends, at sqrt(r_face² +
                    # (length / 2)²), stay behind the kerb at r_kerb; a block without 1 m of depth
                    # and length there is left out (its numbers drawn all the same)
                    r_kerb = 1.0 / abs(road_kappa) - w_road
                    r_face = r_kerb - (cfg.pavement_width + setback)
                    depth = min(depth, 0.6 * r_face)
                    length = min(length, 2 * math.sqrt(max(r_kerb * r_kerb - r_face * r_face, 0.0)))
                e = side * (w_road + cfg.pavement_width + setback + depth / 2)
                tone = uni(0.0, 1.0)
                colour = (150 + 70 * tone + uni(-15, 15), 120 + 60 * tone + uni(-15, 15), 100 + 50 * tone + uni(-15, 15))
                # on a grade the block sits at the height of its middle; its foot reaches down to
                # the lowest point of the pavement along it (the part below ground is hidden)
                sink = max(abs(cfg.grade_before), abs(cfg.grade_after)) * length / 2 if cfg.has_grade else 0.0
                building = SceneObject(BUILDING_BOX, e, s + slot / 2, 0.0, (depth / 2, tall / 2 + sink / 2, length / 2),
                                       h - cfg.kerb_height - tall / 2 + sink / 2, 0.0, False, colour, int(uni(0, 1e6)))
                if depth >= 1.0 and length >= 1.0:
                    objs.append(building)
                s += slot + uni(0.5, 4.0)

    def car(e: float, s0: float, vs: float, reverse: bool) -> None:
        length, width = uni(3.9, 4.8), uni(1.7, 1.9)
        colour = [uni(20, 230) for _ in range(3)]
        clearance, body_h, cabin_h = 0.22, uni(0.7, 0.8), uni(0.5, 0.6)
        seed_tex = int(uni(0, 1e6))
        objs.append(SceneObject(CAR_BODY, e, s0, vs, (width / 2, body_h / 2, length / 2),
                            h - clearance - body_h / 2, 0.0, reverse, tuple(colour), seed_tex))
        objs.append(SceneObject(CAR_CABIN, e, s0, vs, (width / 2 - 0.08, cabin_h / 2, length * 0.28),
                            h - clearance - body_h - cabin_h / 2, -0.15 * length, reverse, tuple(colour),
                            seed_tex))

    if cfg.parking_width > 0:
        for side in (-1.0, 1.0):
            n = count(cfg.parked_cars)
            slots = sorted(uni(0.0, BLOCK) for _ in range(n))
            last = -1e9
            for s in slots:
                if s - last < 6.0:  # no overlapping parked cars
                    continue
                last = s
                car(side * (cfg.lane_width + cfg.parking_width / 2), s_start + s, 0.0, side < 0)
    # one speed per lane and scene, cars spaced along s: moving cars never run into each other
    base = traffic_speed(cfg)
    # explicit odometry keeps the ego speed at any speed_factor: cars slower than the ego vehicle in
    # its lane would be driven through, so then the lane has none
    ego_lane_cars = 1.3 * base >= ego_speed(cfg)
    taken: dict[float, list[float]] = {}
    for _ in range(count(cfg.moving_cars)):
        oncoming = uni(0.0, 1.0) < 0.5
        s0 = s_start + uni(3.0, BLOCK - 3.0)
        lane = -cfg.lane_width / 2 if oncoming else cfg.lane_width / 2
        if not oncoming and (s0 < 10.0 or not ego_lane_cars):
            continue  # same direction, faster than us: only ahead of the ego vehicle
        if any(abs(s0 - other) < 7.0 for other in taken.setdefault(lane, [])):
            continue
        taken[lane].append(s0)
        car(lane, s0, -0.8 * base if oncoming else 1.3 * base, oncoming)
    return objs

