"""Step 4 of the road detection (:mod:`fsof_torch.refinement.auto_road`): the road region from
the windows' decisions, on NumPy arrays at the working resolution.

The road evidence connected to the seed; pixels without evidence take the majority of the
evidence around them where they are testable, the seed's pixels without a decision are road (the
seed's assumption), and the others take the decision found along their line through the focus of
expansion (the road's edges, kerbs and verges run along those lines: a pixel that leaves the
frame takes the decision of the pixel that will be where it is, a pixel too far to test that of
the nearest testable one); then the component connected to the seed, with small enclosed holes
that hold no off-road evidence filled. At full resolution, :func:`follow_edges` then lets the
boundary follow image 1's edges where the windows cannot place it.

Also the detection's mask tensors: :func:`focus_of_expansion` (where the rays meet),
:func:`erode_mask` (the windows seen whole) and :func:`upsample_mask` (back at full size).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from .._check import host_path
from ..geometry.camera import Camera, mounting_matrix

__all__ = ["road_region", "follow_edges", "focus_of_expansion", "erode_mask", "upsample_mask"]


def _components_touching(mask, touch, connectivity: int = 8):
    """The connected components of a (h, w) bool array that contain a pixel of ``touch``."""
    import cv2
    import numpy as np

    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=connectivity)
    keep = np.zeros(count, dtype=bool)
    keep[np.unique(labels[touch & mask])] = True
    keep[0] = False
    return keep[labels]


def _along_rays(decisions, focus: tuple[float, float], inward, todo, steps: int = 16, reach: float = 8.0):
    """Decisions (0 / 1) for the pixels ``todo`` (h, w) bool from a (h, w) int8 map (-1: none):
    the nearest decision on each pixel's line through ``focus`` (x, y in pixels of the map),
    towards the focus where ``inward`` (pixels that leave the frame: the decision of what will be
    where they are), away from it elsewhere (pixels too far to test: the decision of the nearest
    testable ones). Samples at focus + (p − focus) · s, s = reach^(∓i/steps), nearest first.
    Returns (h, w) int8, -1 where no decision was found."""
    import numpy as np

    h, w = decisions.shape
    out = np.full((h, w), -1, dtype=np.int8)
    ys, xs = np.nonzero(todo)
    if ys.size == 0:
        return out
    fx, fy = focus
    factor = np.where(inward[ys, xs], -1.0, 1.0) * (math.log(reach) / steps)
    found = np.full(ys.size, -1, dtype=np.int8)
    dx, dy = xs - fx, ys - fy
    for i in range(1, steps + 1):
        s = np.exp(factor * i)
        x = np.rint(fx + dx * s).astype(np.int64)
        y = np.rint(fy + dy * s).astype(np.int64)
        inside = (x >= 0) & (x < w) & (y >= 0) & (y < h) & (found < 0)
        got = decisions[y[inside], x[inside]]
        found[np.flatnonzero(inside)] = np.where(got >= 0, got, -1)
    out[ys, xs] = found
    return out


def road_region(good, bad, ok, testable, below, seed, focus: tuple[float, float] | None, window: int, max_hole: int):
    """The road (h, w) bool from the window decisions (NumPy arrays; step 4 of the module)."""
    import cv2
    import numpy as np

    closed = cv2.morphologyEx(good.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
    core = _components_touching(closed & ~bad, seed)
    if not core.any():
        return core
    off = bad | (good & ~core)
    # stray off-road windows inside the road must not decide whole rays: only components of at
    # least a window's area count
    count, lab, stats, _ = cv2.connectedComponentsWithStats(off.astype(np.uint8), connectivity=8)
    off = off & (stats[:, cv2.CC_STAT_AREA] >= window * window)[lab]
    evidence = off  # off-road evidence: an enclosed piece that holds some is not a hole
    # undecided but testable (textureless): the majority of the decisions around
    k = 2 * window + 1
    n_road = cv2.boxFilter(core.astype(np.float32), -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    n_off = cv2.boxFilter(off.astype(np.float32), -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    local = below & ~core & ~off & testable & ok & (n_road + n_off > 0)
    road = core | (local & (n_road > n_off))
    off = off | (local & (n_road <= n_off))
    # the seed is road by assumption (its evidence tests it: an implausible seed is flagged): where
    # nothing there says otherwise (a plain lane without texture), it stays road
    road = road | (seed & below & ~off)
    if focus is not None:
        decisions = np.full(road.shape, -1, dtype=np.int8)
        decisions[off] = 0
        decisions[road] = 1
        filled = _along_rays(decisions, focus, below & ~ok, below & (decisions < 0))
        road = road | (filled == 1)
    road = _components_touching(road & below, seed, connectivity=4)
    # small enclosed holes without off-road evidence (a manhole, a patch of shade without
    # texture) are road; a piece the windows found off the road (a distant car) stays out
    count, lab, stats, _ = cv2.connectedComponentsWithStats((~road).astype(np.uint8), connectivity=4)
    fill = stats[:, cv2.CC_STAT_AREA] <= max_hole
    fill[0] = False  # label 0: the road itself
    fill[np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))] = False
    fill[np.unique(lab[evidence])] = False
    return road | fill[lab]


def follow_edges(road, image, below, seed, radius: int, outward: int | None = None):
    """The road (H, W) bool with its boundary moved onto image 1's edges within ``radius`` pixels
    (``outward``, default ``radius``, beyond it).

    A window's decision holds for its centre but is made by all of its pixels: near a car's base
    or a kerb the windows that straddle it are off the road, and the boundary they draw lies up to
    a window's half-width from the edge where road meets obstacle. Here the pixels farther than
    ``radius`` inside the road, and than ``outward`` outside it, keep their decision, and a
    marker-controlled watershed on ``image`` (H, W, 3) uint8 (``cv2.watershed``) gives each pixel between them the
    side it is reached from without crossing an edge. Pixels on the watershed's lines keep their
    decision; the result is the road below the horizon (``below``) connected to ``seed``. A road
    with no pixel farther than ``radius`` from its boundary is returned as it is.
    """
    import cv2
    import numpy as np

    if radius < 1 or not road.any():
        return road
    def disc(r: int):
        return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))

    inside = cv2.erode(road.astype(np.uint8), disc(radius), borderType=cv2.BORDER_REPLICATE) > 0
    outside = cv2.erode((~road).astype(np.uint8), disc(radius if outward is None else outward),
                        borderType=cv2.BORDER_REPLICATE) > 0
    if not inside.any():
        return road
    markers = np.zeros(road.shape, dtype=np.int32)
    markers[inside] = 1
    markers[outside] = 2
    # (cv2.watershed makes the image's outermost pixels lines: flooded on a copy one pixel larger)
    markers = cv2.copyMakeBorder(markers, 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    padded = cv2.copyMakeBorder(np.ascontiguousarray(image), 1, 1, 1, 1, cv2.BORDER_REPLICATE)
    labels = cv2.watershed(padded, markers)[1:-1, 1:-1]
    moved = ((labels == 1) | ((labels == -1) & road)) & below
    return _components_touching(moved, seed, connectivity=4)


def focus_of_expansion(model: str, params: dict[str, Tensor], camera: Camera) -> Tensor:
    """(B, 3) the homogeneous image point the camera moves towards (the epipole in image 1): the
    camera centre at t+1, R_c d in the camera frame of t, projected by K."""
    B = camera.batch_size
    cam = camera.to(torch.float64)

    def get(name: str, default: Tensor) -> Tensor:
        v = params.get(name)
        return default if v is None else torch.as_tensor(v, dtype=torch.float64, device=cam.device).expand(B)

    zero = torch.zeros(B, dtype=torch.float64, device=cam.device)
    d = torch.stack([get("x_d", zero), get("y_d", zero), get("z_d", zero)], dim=-1)
    Rc = mounting_matrix(get("roll", cam.roll), get("pitch", cam.pitch))
    return (cam.K @ (Rc @ d.unsqueeze(-1))).squeeze(-1)


def erode_mask(mask: Tensor, k: int) -> Tensor:
    """(B, 1, h, w) bool eroded by a k × k square (outside the image counts as inside)."""
    if host_path(mask):
        import cv2
        import numpy as np

        kernel = np.ones((k, k), np.uint8)
        planes = [cv2.erode(p, kernel, borderType=cv2.BORDER_REPLICATE) for p in mask[:, 0].numpy().astype(np.uint8)]
        return torch.from_numpy(np.stack(planes)).unsqueeze(1) > 0
    return -F.max_pool2d(-mask.to(torch.float32), k, stride=1, padding=k // 2) > 0.5


def upsample_mask(road: Tensor, level: int, size: tuple[int, int]) -> Tensor:
    """A working-resolution mask back at full size (each pixel its block; the rows and columns
    the pooling dropped copy their neighbours)."""
    if level == 0:
        return road
    m = road.repeat_interleave(2 ** level, dim=-2).repeat_interleave(2 ** level, dim=-1)
    H, W = size
    return F.pad(m.to(torch.uint8), (0, W - m.shape[-1], 0, H - m.shape[-2]), mode="replicate").bool()
