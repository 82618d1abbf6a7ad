"""Road flow on real KITTI data: OpenCV DIS, an ECC road homography, and the refiner's default.

For the shared KITTI 2015 pair 000000 (ground truth) and the shared straight odometry clip (50
pairs, poses), per pair:

- ``DIS``: OpenCV DIS optical flow, ``PRESET_MEDIUM``, on grey uint8 images;
- ``ECC homography``: ``cv2.findTransformECCWithMask`` (OpenCV >= 4.13) with ``MOTION_HOMOGRAPHY``
  (template image 1, input image 2, grey float32, the template's mask the road as drawn on image 1,
  Gaussian 5, 100 iterations or 1e-6), started from a
  RANSAC homography fitted to DIS's flow on the road pixels (``cv2.findHomography``, 3 px); the
  warp maps pixels of image 1 to image 2, so its road flow is π(H p̃) − p. Where ECC fails
  (``cv2.error``) the RANSAC start is kept and the failure counted;
- ``refiner (no odometry)``: ``fsof_torch.FreespaceRefiner()`` on DIS's flow with the images,
  without odometry: what a user gets by default;
- on the clip, the refiner with the clip's road motion from its images (``fsof_torch.fit_sequence``,
  no poses), and with the ground-truth poses as odometry: the ``"plane"`` model's motion
  (``fsof_torch.plane_from_pose``) and the paper's planar motion
  (``fsof_torch.ego_motion_from_pose``), on the pairs whose two frames have a pose; the latter
  held fixed (the default), and as the centres of priors the images may move it from
  (``ImageMotionEstimator(odometry_sigma=ODOMETRY_SIGMA)``).

Each method's road flow replaces DIS's inside the road polygon (road.json), DIS's flow stays
elsewhere. Printed per data set and method: the mean over pairs of the road's census distance (7×7
census bits that differ / 48, image 1 against image 2 warped by the flow: the judge, DESIGN.md §6),
SSIM dissimilarity and L1 (0-255); the road end-point error where there is ground truth; the CPU
time per pair on one thread (for ECC and the refiner: on top of DIS, whose flow they start from); the
pairs more than 0.01 census worse than DIS; and the mean census difference to ECC.

With ``--yaw-deg D`` every pair is turned: image 2 is seen by a camera that also turns by D degrees
about the road's normal between the frames (:func:`turned`; exact at every depth, as a pure
rotation is a homography), the real street's texture in a turn of known motion;
``--pitch-change-deg`` and ``--roll-change-deg`` likewise rotate it about the car's lateral and
forward axes, as the body pitches (braking, a bump) and rolls. With ``--exposure-gain G`` image 2
of every pair is G times as bright (:func:`exposed`: clipped to 0..255 and rounded), as where
the camera's exposure changes between the frames (a shadow, a tunnel's mouth). With ``--slalom
AMPLITUDE_DEG PERIOD`` the clip is seen by a camera that yaws back and forth (:func:`slalomed`):
frame k turned to AMPLITUDE_DEG sin(2π k / PERIOD) degrees about the road's normal, every frame
cut to one window; each frame is turned once, whichever pair it is in, so the clip stays a clip
and ``fit_sequence`` runs on a turn that changes from pair to pair (the KITTI pair is left as
given). With
``--odometry-error SCALE YAW_DEG`` the poses' odometry is made wrong as wheel odometry is: its
translation SCALE times as long, its yaw YAW_DEG degrees a frame off. With ``--resize FACTOR``
every pair is first seen at FACTOR times the resolution (:func:`resized`), as where a network runs
on smaller frames; its end-point errors are in the resized frames' pixels. With ``--reverse`` every
pair's frames are swapped and the clip's pairs taken last to first (:func:`reversed_pair`): the
backward flow a forward-backward check computes, or the street driven in reverse; there is no
ground-truth flow then. With ``--mirror`` every pair is mirrored left to right (:func:`mirrored`):
the same street seen from its other side, its curves turning the other way, with the camera's
principal point and mounting roll mirrored: a check that nothing favours one side. With
``--mask-grow PX`` the methods are given the road polygon grown by PX pixels (negative: shrunk;
:func:`grown`), as a loosely drawn or segmented road mask; the figures stay over the polygon, and
where the mask reaches beyond it the notes give the census (and EPE) there. With ``--crop TOP
BOTTOM LEFT RIGHT`` every pair is first cut to a window (:func:`cropped`), as a pipeline cuts
away the sky or the bonnet. With ``--jpeg QUALITY`` both frames of every pair are stored as JPEG
and read back (:func:`compressed`), as many cameras and data sets store them. Each
``--estimator OPTIONS`` (a JSON object of ``ImageMotionEstimator`` keyword arguments, such as
``'{"smooth_sigma": 0.7}'``) adds a row: the refiner with that estimator, to compare settings on
any of the above.

With ``--pair DIR`` and ``--clip DIR`` it runs on other KITTI data in the same layouts instead
(another KITTI 2015 pair, with or without ground truth; another odometry clip, with or without
poses), e.g. a turning clip: ``python benchmarks/real_road.py --clip path/to/clip``.

Run: ``python benchmarks/real_road.py [--data ../shared/data | --pair DIR --clip DIR] [--pairs N] [--step K] [--roll-deg D] [--yaw-deg D] [--pitch-change-deg D] [--roll-change-deg D] [--exposure-gain G] [--resize FACTOR] [--reverse] [--mirror] [--crop TOP BOTTOM LEFT RIGHT] [--jpeg QUALITY] [--mask-grow PX] [--odometry-error SCALE YAW_DEG] [--no-ecc] [--no-sequence] [--no-turn-screen] [--no-prior-retry] [--no-reverse-screen] [--estimator OPTIONS] [--json PATH]``
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
#: a method more than this much census worse than DIS on a pair counts as worse there
WORSE = 0.01
ECC_CRITERIA = (3, 100, 1e-6)  # cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, epsilon


# -- the methods ----------------------------------------------------------------------------------

def grey_uint8(image: Tensor) -> np.ndarray:
    """(3, H, W) RGB 0..255 -> (H, W) uint8 grey, as DIS gets it (``cv2.cvtColor``)."""
    import cv2

    rgb = image.detach().to(torch.float32).clamp(0, 255).permute(1, 2, 0).cpu().numpy()
    return cv2.cvtColor(rgb.round().astype(np.uint8), cv2.COLOR_RGB2GRAY)


def homography_flow(H: np.ndarray, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """The flow π(H p̃) − p of a homography (pixels of image 1 to image 2) on an (H, W) grid:
    ``(flow (2, H, W) float32, valid (1, H, W) bool)``, valid where the mapped point is in front
    (third coordinate > 0)."""
    rows, cols = size
    Ht = torch.as_tensor(np.asarray(H, dtype=np.float64))
    v, u = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64),
                          indexing="ij")
    p = torch.stack([u, v, torch.ones_like(u)])
    q = torch.einsum("ij,jhw->ihw", Ht, p)
    valid = q[2:] > 1e-9
    w = torch.where(valid, q[2:], torch.ones_like(q[2:]))
    flow = torch.where(valid, q[:2] / w - p[:2], torch.zeros_like(p[:2]))
    return flow.to(torch.float32), valid


def ecc_homography(image1: Tensor, image2: Tensor, road: Tensor, flow_dis: Tensor) -> tuple[np.ndarray, bool]:
    """The road homography of image 1 -> image 2 refined by ECC from a RANSAC start on DIS's road
    flow; returns ``(H (3, 3) float64, ecc_succeeded)`` (the RANSAC start when ECC fails).

    Args: images (3, H, W) RGB 0..255, road (1, H, W) bool, flow_dis (2, H, W) px."""
    import cv2

    v, u = torch.nonzero(road[0], as_tuple=True)
    p = torch.stack([u, v], dim=1).to(torch.float32)
    q = p + flow_dis[:, v, u].T.to(torch.float32)
    H0, _ = cv2.findHomography(p.numpy(), q.numpy(), cv2.RANSAC, 3.0)
    if H0 is None:
        return np.eye(3), False
    g1 = grey_uint8(image1).astype(np.float32)
    g2 = grey_uint8(image2).astype(np.float32)
    mask = road[0].to(torch.uint8).numpy()
    try:
        # The road is drawn on image 1, ECC's template: its mask is the template's (findTransformECC's
        # own mask is the input image's, warped each iteration). A float64 warp raises inside
        # OpenCV: float32 it is.
        _, warp = cv2.findTransformECCWithMask(g1, g2, mask, np.ones_like(mask), H0.astype(np.float32),
                                               cv2.MOTION_HOMOGRAPHY, ECC_CRITERIA, 5)
    except cv2.error:
        return H0, False
    return warp.astype(np.float64), True


def ecc_flow(pair: dict, flow_dis: Tensor) -> tuple[Tensor, dict]:
    """ECC's road flow (2, H, W) (DIS's where the homography maps behind the camera)."""
    H, ok = ecc_homography(pair["image1"], pair["image2"], given_mask(pair), flow_dis)
    flow, valid = homography_flow(H, tuple(flow_dis.shape[-2:]))
    return torch.where(valid, flow, flow_dis), {"ecc_failed": not ok}


def refiner_flow(pair: dict, flow_dis: Tensor, odometry: Any = None, **options: Any) -> tuple[Tensor, dict]:
    """The default ``FreespaceRefiner()`` on DIS's flow, with the images, and ``odometry``
    (``options``: the image estimator's, ``ImageMotionEstimator(**options)``)."""
    from fsof_torch import FreespaceRefiner, ImageMotionEstimator

    images = (pair["image1"][None], pair["image2"][None])
    refiner = FreespaceRefiner(estimator=ImageMotionEstimator(**options)) if options else FreespaceRefiner()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an unrefined pair is counted, not warned about
        out = refiner(flow_dis[None], given_mask(pair)[None], pair["camera"], odometry, images=images)
    motion = {"z_d": float(out.odometry["z_d"][0]), "yaw_deg": math.degrees(float(out.odometry["yaw"][0]))}
    info = {"refined": bool(out.refined[0]), "motion": motion, "model_flow": out.flow_model[0].detach()}
    # (an estimate that succeeded, whether or not the gate then used it: its flow's own error counts)
    info["estimated"] = bool(out.refined[0]) or (out.fit is not None and bool(out.fit.success[0]))
    if out.gate is not None:
        info["cells_kept"] = int(out.gate.cells_kept[0])
        # (the JSON's per-pair results: the gate's mean ring census of each flow over the mask,
        # and whether the images confirmed the model there)
        info["gate"] = {"census_model": float(out.gate.cost_model[0]), "census_prediction":
                        float(out.gate.cost_prediction[0]), "confirmed": bool(out.gate.confirmed[0]),
                        "informative": bool(out.gate.informative[0])}
    return out.flow[0].detach(), info


def plane_odometry(pair: dict) -> dict:
    """The ground-truth relative pose as the ``"plane"`` model's motion (with ``--odometry-error``,
    its translation scaled and its yaw shifted)."""
    from fsof_torch import plane_from_pose

    T = pair["relative_pose"][None].to(torch.float64)
    motion = plane_from_pose(T, pair["camera"].to(torch.float64))
    scale, yaw = pair.get("odometry_error", (1.0, 0.0))
    motion.update({k: motion[k] * scale for k in ("x_d", "y_d", "z_d")}, yaw=motion["yaw"] + math.radians(yaw))
    return {"model": "plane", **motion}


def paper_odometry(pair: dict):
    """The ground-truth relative pose projected on the paper's planar motion (x_d, z_d, yaw) (with
    ``--odometry-error``, its translation scaled and its yaw shifted)."""
    from fsof_torch import ego_motion_from_pose

    motion = ego_motion_from_pose(pair["relative_pose"][None].to(torch.float64), pair["camera"].to(torch.float64))
    scale, yaw = pair.get("odometry_error", (1.0, 0.0))
    return motion._replace(x_d=motion.x_d * scale, z_d=motion.z_d * scale, yaw=motion.yaw + math.radians(yaw))


#: the widths the images may move the poses' planar motion by (``ImageMotionEstimator``'s
#: ``odometry_sigma``): about what wheel odometry is off by in a frame at city speed (a few
#: percent of a metre's step, a yaw-rate bias of a few tenths of a degree a second and more)
ODOMETRY_SIGMA = {"x_d": 0.05, "z_d": 0.05, "yaw": math.radians(0.2)}


#: name -> (what it needs, method(pair, dis flow) -> (flow, info)); DIS itself is measured apart
METHODS: dict[str, tuple[str | None, Callable[[dict, Tensor], tuple[Tensor, dict]]]] = {
    "ECC homography": (None, ecc_flow),
    "refiner (no odometry)": (None, refiner_flow),
    "refiner, poses ('plane')": ("relative_pose", lambda pair, dis: refiner_flow(pair, dis, plane_odometry(pair))),
    "refiner, poses (paper's planar)": ("relative_pose",
                                        lambda pair, dis: refiner_flow(pair, dis, paper_odometry(pair))),
    "refiner, poses (paper's planar) as priors": (
        "relative_pose", lambda pair, dis: refiner_flow(pair, dis, paper_odometry(pair), odometry_sigma=ODOMETRY_SIGMA)),
}


#: ``--no-turn-screen``: the default refiner without the image fit's screen of turns, and both
#: without the start from DIS's flow (the images alone, as where a network's flow misses a turn)
TURN_ROWS = {"refiner, turn_starts=()": {"turn_starts": ()},
             "refiner, flow_start=False": {"flow_start": False},
             "refiner, flow_start=False, turn_starts=()": {"flow_start": False, "turn_starts": ()}}
#: ``--no-prior-retry``: the default refiner without the image fit's retry without the coarsest
#: level's prior
PRIOR_ROWS = {"refiner, retry_without_prior=False": {"retry_without_prior": False}}
#: ``--no-reverse-screen``: the default refiner without the image fit's screen of steps backwards
REVERSE_ROWS = {"refiner, reverse_starts=()": {"reverse_starts": ()}}


def clip_method(pairs: list[tuple[str, Callable[[], dict]]], progress: bool) -> tuple[str, Callable, dict]:
    """The refiner with the clip's road motion from its images (``fsof_torch.fit_sequence``: the
    mounting calibrated over the clip, the motion carried forward, the attitude smoothed; no
    poses), each pair refined with its ``"plane"`` motion and the calibrated camera. Its time per
    pair includes the clip fit's share (its CPU time over the clip / the pairs). Returns the
    method's name, the method and the calibrated mounting (``pitch_deg``, ``roll_deg``), which it
    prints."""
    from fsof_torch import fit_sequence

    loaded = [load() for _, load in pairs]
    frames = [p["image1"] for p in loaded] + [loaded[-1]["image2"]]
    t0 = time.process_time()
    seq = fit_sequence(frames, [given_mask(p) for p in loaded], loaded[0]["camera"].to(torch.float64),
                       progress=progress)
    share = (time.process_time() - t0) / len(loaded)
    mounting = {"pitch_deg": math.degrees(seq.mounting["pitch"]), "roll_deg": math.degrees(seq.mounting["roll"])}
    print(f"fit_sequence calibrated the mounting at pitch {mounting['pitch_deg']:+.3f} deg, "
          f"roll {mounting['roll_deg']:+.3f} deg (no poses)")
    motion = {name: {"model": "plane", **{k: v[i:i + 1] for k, v in seq.params.items()}}
              for i, (name, _) in enumerate(pairs)}

    def method(pair: dict, dis: Tensor) -> tuple[Tensor, dict]:
        t = time.process_time()
        flow, info = refiner_flow({**pair, "camera": seq.camera}, dis, motion[pair["name"]])
        return flow, {**info, "seconds": time.process_time() - t + share}

    return "refiner, clip motion (fit_sequence)", method, mounting


# -- measuring ------------------------------------------------------------------------------------

def given_mask(pair: dict) -> Tensor:
    """The mask the methods are given: the road polygon, or with ``--mask-grow`` the polygon grown
    or shrunk (:func:`grown`)."""
    return pair.get("mask", pair["road"])


def road_errors(pair: dict, flow: Tensor, flow_dis: Tensor) -> dict[str, float]:
    """Road census, SSIM, L1 (and EPE with ground truth) of ``flow`` inside the road, DIS's flow
    elsewhere (the windows of census and SSIM near the polygon's edge see both). A method's flow
    counts inside the mask it was given (:func:`given_mask`); where that mask reaches beyond the
    road, the census there (``ring_census``) and, with ground truth, the EPE there (``ring_epe``)."""
    from fsof_torch import endpoint_error, photometric_errors

    road, given = pair["road"][None], given_mask(pair)[None]
    combined = torch.where(given, flow[None], flow_dis[None])
    images = pair["image1"][None], pair["image2"][None]
    errors = photometric_errors(*images, combined, road, return_count=True)
    out = {kind: float(mean[0]) for kind, (mean, _) in errors.items()}
    out["n_census"] = int(errors["census"][1][0])
    if pair.get("flow") is not None:
        out["epe"], out["n_epe"] = road_epe(pair, combined[0])
    ring = given & ~road
    if bool(ring.any()):
        out["ring_census"] = float(photometric_errors(*images, combined, ring, kinds=("census",))["census"][0])
        if pair.get("flow") is not None and bool((ring & pair["valid"][None]).any()):
            out["ring_epe"] = float(endpoint_error(combined, pair["flow"][None].to(flow.dtype), ring,
                                                   pair["valid"][None])[0])
    return out


def road_epe(pair: dict, flow: Tensor) -> tuple[float, int]:
    """The end-point error of ``flow`` (2, H, W) over the road pixels with ground truth, and their
    number."""
    from fsof_torch import endpoint_error

    epe, n = endpoint_error(flow[None], pair["flow"][None].to(flow.dtype), pair["road"][None], pair["valid"][None],
                            return_count=True)
    return float(epe[0]), int(n[0])


def run_pair(pair: dict, methods: dict) -> dict[str, dict]:
    """DIS and every method of ``methods`` that the pair has inputs for: road errors, seconds
    (each method's own, on top of DIS for the others; CPU time of the process, which on one
    thread is the time on an idle core and does not count waiting for a busy one) and the
    method's info."""
    from refine.sources import dis_flow

    t0 = time.process_time()
    dis = dis_flow(pair["image1"], pair["image2"])
    seconds = time.process_time() - t0
    results = {"DIS": {**road_errors(pair, dis, dis), "seconds": seconds}}
    for name, (needs, method) in methods.items():
        if needs is not None and pair.get(needs) is None:
            continue
        t0 = time.process_time()
        flow, info = method(pair, dis)
        seconds = time.process_time() - t0
        model_flow, estimated = info.pop("model_flow", None), info.pop("estimated", True)
        results[name] = {**road_errors(pair, flow, dis), "seconds": seconds, **info}
        if model_flow is not None and "epe" in results[name] and estimated:
            # the model flow on the whole road, before the gate kept the prediction anywhere (also
            # where the gate kept it everywhere: the estimate succeeded)
            results[name]["epe_model"] = road_epe(pair, model_flow)[0]
    return results


def summarize(per_pair: list[dict[str, dict]]) -> list[dict[str, Any]]:
    """One row per method over the pairs it ran on: means, worse-than-DIS count, ECC difference."""
    names = list(dict.fromkeys(n for r in per_pair for n in r))
    rows = []
    for name in names:
        runs = [r for r in per_pair if name in r]
        row: dict[str, Any] = {"method": name, "pairs": len(runs)}
        for key in ("census", "ssim", "l1", "epe", "epe_model", "ring_census", "ring_epe", "seconds"):
            values = [r[name][key] for r in runs if key in r[name]]
            if values:
                row[key] = float(np.mean(values))
        row["worse_than_dis"] = sum(r[name]["census"] > r["DIS"]["census"] + WORSE for r in runs)
        row["max_worse_than_dis"] = max(r[name]["census"] - r["DIS"]["census"] for r in runs)
        with_ecc = [r for r in runs if "ECC homography" in r]
        if with_ecc:
            row["minus_ecc"] = float(np.mean([r[name]["census"] - r["ECC homography"]["census"] for r in with_ecc]))
        for flag in ("ecc_failed", "refined"):
            if any(flag in r[name] for r in runs):
                row[flag] = sum(bool(r[name].get(flag)) for r in runs)
        if any("cells_kept" in r[name] for r in runs):
            row["cells_kept"] = sum(r[name].get("cells_kept", 0) for r in runs)
        rows.append(row)
    return rows


def images_against_poses(per_pair: list[dict[str, dict]]) -> str | None:
    """Where the images and the poses disagree: over the pairs that both the refiner without
    odometry and the one with the poses' planar motion held refined, and whose poses move by more
    than a millimetre (not a frame repeated), the images' forward step over the poses' (at the nominal camera height) and
    the images' yaw minus the poses'."""
    images, poses = "refiner (no odometry)", "refiner, poses (paper's planar)"
    both = [(r[images]["motion"], r[poses]["motion"]) for r in per_pair
            if images in r and poses in r and r[images]["refined"] and r[poses]["refined"]
            and abs(r[poses]["motion"]["z_d"]) > 1e-3]  # (a frame repeated: its poses' step rounds to ~1e-17 m)
    if not both:
        return None
    ratio = np.array([a["z_d"] / b["z_d"] for a, b in both])
    yaw = np.array([a["yaw_deg"] - b["yaw_deg"] for a, b in both])
    return (f"The images against the poses ({len(both)} pairs): forward step x {ratio.min():.3f} to "
            f"{ratio.max():.3f} (median {np.median(ratio):.3f}); yaw {yaw.min():+.3f}° to {yaw.max():+.3f}° a frame "
            f"(median |difference| {np.median(np.abs(yaw)):.3f}°)")


def table(rows: list[dict[str, Any]]) -> str:
    """The rows as a Markdown table."""
    def f(x, digits):
        return "–" if x is None else f"{x:.{digits}f}"

    head = ["method", "pairs", "road census", "road SSIM", "road L1", "road EPE (px)", "CPU s / pair",
            f"pairs > {WORSE} worse than DIS", "census − ECC", "notes"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        notes = []
        if "ecc_failed" in r:
            notes.append(f"ECC failed on {r['ecc_failed']}")
        if "refined" in r:
            notes.append(f"refined {r['refined']}/{r['pairs']}")
        if r.get("cells_kept"):
            notes.append(f"the gate kept the prediction in {r['cells_kept']} cell(s)")
        if "epe_model" in r:
            notes.append(f"model alone EPE {r['epe_model']:.2f}")
        if "ring_census" in r:
            ring_epe = f", EPE {r['ring_epe']:.2f}" if "ring_epe" in r else ""
            notes.append(f"in the mask beyond the road: census {r['ring_census']:.4f}{ring_epe}")
        worse = "–" if r["method"] == "DIS" else f"{r['worse_than_dis']} (max {r['max_worse_than_dis']:+.3f})"
        lines.append("| " + " | ".join([r["method"], str(r["pairs"]), f(r.get("census"), 4), f(r.get("ssim"), 4),
                                         f(r.get("l1"), 2), f(r.get("epe"), 2), f(r.get("seconds"), 3), worse,
                                         f(r.get("minus_ecc"), 4) if "minus_ecc" in r else "–",
                                         "; ".join(notes)]) + " |")
    return "\n".join(lines)


# -- the data -------------------------------------------------------------------------------------

def kitti15(root: Path, height: float, roll_deg: float = 0.0) -> list[tuple[str, Callable[[], dict]]]:
    """A KITTI 2015 pair (``kitti15_000000``'s layout): images, camera (P_rect_02, ``height`` m
    over the road, rolled by ``roll_deg``), road.json, ground truth where flow_noc_10.png is there;
    named after its folder."""
    from fsof_torch.datasets import KittiSampleDataset

    dataset = KittiSampleDataset(root, camera_height=height, roll=math.radians(roll_deg), camera_dtype=torch.float64)
    return [(dataset.pairs[0].name, lambda: dataset[0])]


def clip_frames(root: Path | None) -> int | None:
    """The number of frames of the clip ``root`` (``image_l/``, in the library's frame order); None
    where there is no clip to count (no folder, fewer than two images: the run reports it)."""
    from fsof_torch.data.folders import list_images

    if root is None or not (root / "image_l").is_dir():
        return None
    try:
        return len(list_images(root / "image_l"))
    except ValueError:
        return None


def odometry_clip(root: Path, height: float, pitch_deg: float, step: int = 1,
                  roll_deg: float = 0.0, steps: list[int] | None = None) -> list[tuple[str, Callable[[], dict]]]:
    """The straight clip: pairs of images ``step`` frames apart, (0, step), (step, 2 step), ...
    (every ``step``-th frame: the clip driven ``step`` times as fast, or recorded at 1 / ``step``
    of its rate), with the relative pose inverse(P_b) @ P_a of its frames a and b where poses.txt
    has both (line n for frame NNNNNN = n, by the file names, not by position; none without
    poses.txt: the methods that need poses are left out; a poses.txt with no line for any frame
    is a ValueError naming ``poses``). The camera: ``height`` m over the road,
    pitched by ``pitch_deg`` and rolled by ``roll_deg``. ``steps`` (instead of ``step``): the
    pairs' frames are these many apart in turn, from frame 0 (a car speeding up and braking; 0: a
    frame repeated, the car stopped), each pair named by its place and its two frames; the
    positions must lie in the clip (a ValueError naming ``steps``)."""
    from fsof_torch import read_kitti_poses
    from fsof_torch.datasets import ImageFolderDataset

    dataset = ImageFolderDataset(root / "image_l", root / "calib.txt", cam=0, camera_height=height,
                                 roll=math.radians(roll_deg), pitch=math.radians(pitch_deg), road=root / "road.json",
                                 camera_dtype=torch.float64,
                                 step=step)
    poses = read_kitti_poses(root / "poses.txt") if (root / "poses.txt").is_file() else torch.empty(0, 4, 4)

    def frame(path: Path) -> int | None:
        return int(path.stem) if path.stem.isdigit() else None

    if len(poses) and not any(n is not None and n < len(poses) for n in map(frame, dataset.frames)):
        # (frames numbered from their place in a sequence, poses cut to the clip: no pair would
        # have its poses, and the methods that need them would be left out unsaid)
        raise ValueError(f"poses: {str(root / 'poses.txt')!r} has {len(poses)} poses (line n for frame NNNNNN = n), "
                         f"none for the clip's frames {dataset.frames[0].name} to {dataset.frames[-1].name}: "
                         f"give the sequence's poses from its first frame on, or number the frames as the lines")

    if steps is not None:
        positions = [0]
        for k in steps:
            positions.append(positions[-1] + k)
        if positions[-1] >= len(dataset.frames):
            raise ValueError(f"steps: frames {positions[-1]} frames apart in all, beyond the clip's "
                             f"{len(dataset.frames)} frames")
        return [(f"{k}:{dataset.frames[a].stem}-{dataset.frames[b].stem}", stepped_loader(dataset, poses, a, b))
                for k, (a, b) in enumerate(zip(positions, positions[1:]))]

    def loader(i: int) -> Callable[[], dict]:
        a, b = frame(dataset.pairs[i].image1), frame(dataset.pairs[i].image2)

        def with_pose() -> dict:
            pair = dataset[i]
            known = a is not None and b is not None and max(a, b) < len(poses)
            pair["relative_pose"] = torch.linalg.inv(poses[b]) @ poses[a] if known else None
            pair["positions"] = (i, i + step)  # (the frames' places in the clip)
            return pair
        return with_pose

    return [(p.name, loader(i)) for i, p in enumerate(dataset.pairs) if i % step == 0]


def stepped_loader(dataset: Any, poses: Tensor, a: int, b: int) -> Callable[[], dict]:
    """The pair of the clip's frames at places ``a`` and ``b`` (``a`` <= ``b``; equal: a frame
    repeated) of ``dataset`` (consecutive pairs), with its relative pose as :func:`odometry_clip`
    gives it and its places (``positions``)."""

    def holding(position: int) -> tuple[dict, str]:
        """The dataset's item that holds the frame at ``position``, and its key there."""
        return (dataset[position], "image1") if position < len(dataset.pairs) else (dataset[position - 1], "image2")

    def number(position: int) -> int | None:
        stem = dataset.frames[position].stem
        return int(stem) if stem.isdigit() else None

    def load() -> dict:
        pair, key = holding(a)  # (its camera and road too)
        # (consecutive frames: the item itself, read once)
        other, other_key = (pair, "image2") if key == "image1" and b == a + 1 else holding(b)
        pair["image1"], pair["image2"] = pair[key], other[other_key]
        n_a, n_b = number(a), number(b)
        known = n_a is not None and n_b is not None and max(n_a, n_b) < len(poses)
        pair["relative_pose"] = torch.linalg.inv(poses[n_b]) @ poses[n_a] if known else None
        pair["positions"] = (a, b)
        return pair
    return load


def turned(pair: dict, yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0,
           window: tuple[int, int, int, int] | None = None) -> dict:
    """``pair`` seen by a camera that also turns by ``yaw_deg`` degrees about the road's normal
    between the frames (positive: to the right, the road models' yaw), then by ``pitch_deg`` and
    ``roll_deg`` about the car's lateral and forward axes (the ``"plane"`` model's pitch_change
    and roll_change, in its signs): image 2 resampled through the rotation's homography
    K Rᵀ K⁻¹ (Lanczos, OpenCV; clipped to 0..255), both frames cropped to the largest
    window in which the turned image 2 is defined, the camera cropped with them, and the
    ground-truth flow and relative pose composed with the turn. ``window``: (r0, r1, c0, c1) to
    crop to instead, inside the defined region."""
    H, R = turn_homography(pair["camera"], yaw_deg, pitch_deg, roll_deg)  # image 2's pixels -> the turned camera's
    rows, cols = pair["image2"].shape[-2:]
    v, u = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64),
                          indexing="ij")
    defined = defined_under(H, rows, cols)
    # the largest window, with up to a fifth of the rows cut at the top and at the bottom, in
    # which every pixel of the turned image 2 is defined (a turn tilts the image's edges)
    r0, r1, c0, c1 = defined_window(defined) if window is None else window
    if r1 <= r0 or c1 <= c0:
        raise ValueError(f"the turn ({yaw_deg}°, {pitch_deg}°, {roll_deg}°) leaves no window of image 2 defined")
    if not bool(defined[r0:r1, c0:c1].all()) or min(r0, c0) < 0:
        raise ValueError(f"window: {window} reaches beyond where the turned image 2 is defined")
    out = {**pair, "camera": pair["camera"].cropped(c0, r0, cols - c1, rows - r1)}
    out["image1"] = pair["image1"][..., r0:r1, c0:c1].contiguous()
    out["image2"] = warped_frame(pair["image2"], H, (r0, r1, c0, c1))
    for key in ("road", "valid"):
        if pair.get(key) is not None:
            out[key] = pair[key][..., r0:r1, c0:c1].contiguous()
    if pair.get("flow") is not None:
        f = pair["flow"].to(torch.float64)
        q = torch.einsum("ij,jhw->ihw", H, torch.stack([u + f[0], v + f[1], torch.ones_like(u)]))
        out["flow"] = torch.stack([q[0] / q[2] - u, q[1] / q[2] - v])[..., r0:r1, c0:c1].to(pair["flow"].dtype).contiguous()
    if pair.get("relative_pose") is not None:
        turn = torch.eye(4, dtype=torch.float64)
        turn[:3, :3] = R.T
        out["relative_pose"] = turn @ pair["relative_pose"].to(torch.float64)
    return out


def turn_homography(camera: Any, yaw_deg: float, pitch_deg: float = 0.0,
                    roll_deg: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The homography K Rᵀ K⁻¹ (float64) that maps a frame's pixels to those of the camera turned by
    ``yaw_deg`` about the road's normal, then by ``pitch_deg`` and ``roll_deg`` about the car's
    lateral and forward axes (``camera``'s mounting gives the axes), and the rotation R. Each
    turn is the exponential of its axis-angle's skew matrix (exact to float64's rounding: kornia
    0.8's axis_angle_to_rotation_matrix divides by the angle plus 1e-6, a rotation 1e-5 off)."""
    from fsof_torch.geometry.camera import mounting_matrix

    cam = camera.to(torch.float64)
    K = cam.K.reshape(-1, 3, 3)[0]
    # the car's axes in the camera: lateral, down (the road's normal) and forward
    axes = mounting_matrix(cam.roll.reshape(-1)[:1], cam.pitch.reshape(-1)[:1])[0].T
    angles = torch.tensor([pitch_deg, yaw_deg, roll_deg], dtype=torch.float64).deg2rad()
    wx, wy, wz = (axes * angles.unsqueeze(-1)).unbind(-1)
    zero = torch.zeros_like(wx)
    skew = torch.stack([zero, -wz, wy, wz, zero, -wx, -wy, wx, zero], -1).reshape(3, 3, 3)
    Rs = torch.linalg.matrix_exp(skew)
    R = Rs[1] @ Rs[0] @ Rs[2]
    return K @ R.T @ torch.linalg.inv(K), R


def defined_under(H: torch.Tensor, rows: int, cols: int) -> torch.Tensor:
    """(rows, cols) bool: the pixels of a frame warped by ``H`` that come from inside the frame."""
    v, u = torch.meshgrid(torch.arange(rows, dtype=torch.float64), torch.arange(cols, dtype=torch.float64),
                          indexing="ij")
    source = torch.einsum("ij,jhw->ihw", torch.linalg.inv(H), torch.stack([u, v, torch.ones_like(u)]))
    x, y = source[0] / source[2], source[1] / source[2]
    eps = 1e-6  # (the rounding of H)
    return (source[2] > 0) & (x >= -eps) & (x <= cols - 1 + eps) & (y >= -eps) & (y <= rows - 1 + eps)


def warped_frame(image: torch.Tensor, H: torch.Tensor, window: tuple[int, int, int, int]) -> torch.Tensor:
    """``image`` (C, H, W) warped by the homography ``H`` and cut to ``window`` (r0, r1, c0, c1), in its
    dtype: Lanczos (8 × 8 taps), clipped to 0..255 (its overshoot): bilinear weights would blur the
    frame by up to half its finest detail, and that blur, not the motion, would show in the census
    and in the auto road."""
    import cv2

    rows, cols = image.shape[-2:]
    r0, r1, c0, c1 = window
    frame = image.to(torch.float32).permute(1, 2, 0).contiguous().numpy()
    warped = cv2.warpPerspective(frame, H.numpy(), (cols, rows), flags=cv2.INTER_LANCZOS4).clip(0, 255)
    warped = warped.reshape(rows, cols, -1)  # (OpenCV drops a single channel's axis)
    return torch.from_numpy(warped[r0:r1, c0:c1]).permute(2, 0, 1).to(image.dtype).contiguous()


def slalom_yaw(position: int, amplitude: float, period: float) -> float:
    """The heading (degrees) of the camera at frame ``position`` of a clip that yaws back and forth:
    ``amplitude`` sin(2π ``position`` / ``period``)."""
    return amplitude * math.sin(2 * math.pi * position / period)


def slalom_window(camera: Any, size: tuple[int, int], frames: int, amplitude: float,
                  period: float) -> tuple[int, int, int, int]:
    """The largest window (r0, r1, c0, c1) of :func:`defined_window` in which every one of the clip's
    ``frames`` frames (``size`` (rows, cols)), turned to its :func:`slalom_yaw`, is defined."""
    defined = torch.ones(size, dtype=torch.bool)
    for position in range(frames):
        defined &= defined_under(turn_homography(camera, slalom_yaw(position, amplitude, period))[0], *size)
    window = defined_window(defined)
    if window[1] - window[0] < 32 or window[3] - window[2] < 32:
        raise UnfitOption(f"--slalom: turns of up to {amplitude:g}° leave no window of 32 × 32 pixels or more in "
                          f"which every frame is defined")
    return window


def slalomed(pair: dict, amplitude: float, period: float, window: tuple[int, int, int, int]) -> dict:
    """A clip's pair seen by a camera that also yaws back and forth about the road's normal: frame
    k turned to :func:`slalom_yaw` (k its position in the clip, ``pair["positions"]`` for the
    pair's two frames), both frames, the road and the camera cut to ``window`` (one for the whole
    clip, :func:`slalom_window`), the relative pose composed with the two headings. Each frame is
    turned by its own heading, whichever pair it is in: image 2 of a pair is image 1 of the next,
    a clip to fit (fit_sequence), whose turn a frame changes from pair to pair."""
    import cv2

    r0, r1, c0, c1 = window
    (H1, R1), (H2, R2) = (turn_homography(pair["camera"], slalom_yaw(k, amplitude, period)) for k in pair["positions"])
    rows, cols = pair["image1"].shape[-2:]
    out = {**pair, "camera": pair["camera"].cropped(c0, r0, cols - c1, rows - r1), "flow": None, "valid": None}
    out["image1"], out["image2"] = warped_frame(pair["image1"], H1, window), warped_frame(pair["image2"], H2, window)
    road = cv2.warpPerspective(pair["road"][0].to(torch.uint8).numpy(), H1.numpy(), (cols, rows),
                               flags=cv2.INTER_NEAREST)
    out["road"] = torch.from_numpy(road[r0:r1, c0:c1].copy()).bool().unsqueeze(0)
    if pair.get("relative_pose") is not None:
        turn1, turn2 = torch.eye(4, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
        turn1[:3, :3], turn2[:3, :3] = R1, R2.T
        out["relative_pose"] = turn2 @ pair["relative_pose"].to(torch.float64) @ turn1
    return out


def defined_window(defined: torch.Tensor) -> tuple[int, int, int, int]:
    """The largest window (r0, r1, c0, c1) in which ``defined`` (rows, cols) bool holds everywhere,
    with up to a fifth of the rows cut at the top and at the bottom, each cut any number of rows (a
    turn bends the top and bottom rows by fractions of a pixel: a cut in coarse steps would take
    the nearest road with them), and the longest run of columns full between the cuts. (0, 0, 0, 0)
    where none."""
    rows = defined.shape[0]
    half = rows // 2
    index = torch.arange(rows).unsqueeze(1)
    # per column, the rows a window must start below and end above (undefined pixels lie in the
    # top or the bottom half; a window's ends lie within a fifth of the rows of the frame's)
    start = torch.where(~defined[:half], index[:half] + 1, 0).amax(0)
    end = torch.where(~defined[half:], index[half:], rows).amin(0)
    cuts = torch.arange(rows // 5 + 1)
    full = (start <= cuts[:, None, None]) & (end >= rows - cuts[None, :, None])  # (top, bottom, column)
    # the run of full columns ending at each column: its distance from the last column not full
    column = torch.arange(full.shape[-1])
    run = column - torch.where(full, -1, column).cummax(-1).values
    longest, last = run.max(-1)
    area = (rows - cuts[:, None] - cuts[None, :]) * longest
    best = int(area.flatten().argmax())  # (the first of equal areas: the fewest rows cut at the top)
    top, bottom = divmod(best, len(cuts))
    if int(area[top, bottom]) == 0:
        return 0, 0, 0, 0
    c1 = int(last[top, bottom]) + 1
    return top, rows - bottom, c1 - int(longest[top, bottom]), c1


def reversed_pair(pair: dict) -> dict:
    """``pair`` with its frames swapped: the backward flow (image 2 to image 1, as a
    forward-backward check computes it), or the same street driven in reverse. The relative pose
    is inverted; the ground-truth flow, which is forward, is dropped (no end-point error); the road
    polygon stays the one drawn on the forward pair's image 1, which the same road fills."""
    out = {**pair, "image1": pair["image2"], "image2": pair["image1"], "flow": None, "valid": None}
    if pair.get("relative_pose") is not None:
        out["relative_pose"] = torch.linalg.inv(pair["relative_pose"].to(torch.float64))
    return out


def mirrored(pair: dict) -> dict:
    """``pair`` mirrored left to right: the same street as a car driving on its other side would see
    it, a curve turning the other way. Both frames, the road, the ground-truth flow (its horizontal
    component negated) and its valid pixels flipped; the camera's principal point mirrored
    (c_x' = W − 1 − c_x, a skew negated) and its mounting roll negated (a roll given with
    ``--roll-deg`` too); the relative pose conjugated by the reflection of the camera's x axis."""
    flip = lambda x: x.flip(-1).contiguous()  # noqa: E731
    cam = pair["camera"]
    W = pair["image1"].shape[-1]
    K = cam.K.clone()
    K[..., 0, 2] = (W - 1) - K[..., 0, 2]
    K[..., 0, 1] = -K[..., 0, 1]  # (a skew turns over with the x axis)
    out = {**pair, "camera": cam.replace(K=K, roll=-cam.roll)}
    for key in ("image1", "image2", "road", "valid"):
        if pair.get(key) is not None:
            out[key] = flip(pair[key])
    if pair.get("flow") is not None:
        f = flip(pair["flow"])
        out["flow"] = torch.stack([-f[0], f[1]]).contiguous()
    if pair.get("relative_pose") is not None:
        S = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=torch.float64))
        out["relative_pose"] = S @ pair["relative_pose"].to(torch.float64) @ S
    return out


def grown(pair: dict, pixels: int) -> dict:
    """``pair`` with a ``mask`` for the methods: the road polygon grown by ``pixels`` (OpenCV's
    dilation by a disc of that radius; negative: shrunk by the erosion), as a loosely drawn or
    segmented road mask takes in kerbs, verges and cars or leaves out the road's edges. The
    figures stay over the polygon (:func:`road_errors`)."""
    import cv2

    if pixels == 0:
        return dict(pair)
    road = pair["road"][0].numpy().astype(np.uint8)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * abs(pixels) + 1,) * 2)
    mask = cv2.dilate(road, disc) if pixels > 0 else cv2.erode(road, disc)
    if not mask.any():
        raise EmptyMask(f"--mask-grow: a road polygon shrunk by {-pixels} px is empty: shrink it less")
    return {**pair, "mask": torch.from_numpy(mask.astype(bool))[None]}


#: ``--mask-grow``'s largest growth or shrinkage (px): a road mask off by more is not a loose mask
MAX_GROW = 100


class UnfitOption(ValueError):
    """An option the data cannot take (a crop larger than the frame, a polygon shrunk to nothing):
    found on one pair of each data set before any work, the run stops with exit status 2."""


class EmptyMask(UnfitOption):
    """A road polygon shrunk to nothing (``--mask-grow``)."""


class UnfitData(UnfitOption):
    """A data folder the library cannot read (a calibration without the camera, frames of another
    size than it or than each other, a malformed road.json or poses.txt): the library's message,
    after the option that named the folder (``--clip``, ``--pair``, ``--data``); the run stops
    with exit status 2, before any work where the first pair shows it."""


def checked_data(option: str, read: Callable[[], list[tuple[str, Callable[[], dict]]]]
                 ) -> list[tuple[str, Callable[[], dict]]]:
    """``read()``'s pairs, the errors of reading the folder and of loading each pair (the
    library's ``ValueError`` and ``FileNotFoundError``, which name the file), and a road polygon
    that covers no pixel of the frames, as :class:`UnfitData` naming ``option``."""
    def unfit(err: Exception) -> UnfitData:
        return UnfitData(f"{option}: {err}")

    try:
        pairs = read()
    except (ValueError, FileNotFoundError) as err:
        raise unfit(err) from None

    def load(inner: Callable[[], dict]) -> dict:
        try:
            pair = inner()
        except (ValueError, FileNotFoundError) as err:
            raise unfit(err) from None
        if not bool(pair["road"].any()):  # (the figures are over the polygon: each would read 0 over no pixel)
            rows, cols = pair["image1"].shape[-2:]
            raise unfit(f"road.json: its road polygon covers no pixel of the {rows} x {cols} frames")
        return pair

    return [(name, lambda inner=inner: load(inner)) for name, inner in pairs]


def turned_by_options(pair: dict, turn: tuple[float, float, float]) -> dict:
    """:func:`turned` by ``turn`` (``--yaw-deg``, ``--pitch-change-deg``, ``--roll-change-deg``); a
    turn that leaves no window of the frame defined (:func:`defined_window` cuts at most a fifth of
    the rows at the top and at the bottom: a pitch change of about 6 degrees on KITTI's frames) is
    an :class:`UnfitOption` naming the options."""
    try:
        return turned(pair, *turn)
    except UnfitOption:
        raise
    except ValueError as err:
        raise UnfitOption(f"--yaw-deg, --pitch-change-deg, --roll-change-deg: {err} (the turned frames may lose "
                          f"at most a fifth of their rows at the top and at the bottom): turn less") from None


def exposed(pair: dict, gain: float) -> dict:
    """``pair`` with image 2 ``gain`` times as bright: clipped to 0..255 and rounded, as an 8-bit
    camera records a change of exposure between the frames."""
    image2 = (pair["image2"].to(torch.float32) * gain).clamp(0, 255).round()
    return {**pair, "image2": image2.to(pair["image2"].dtype)}


def compressed(pair: dict, quality: int) -> dict:
    """``pair`` with both frames stored as JPEG at ``quality`` (OpenCV's encoder, 1..100) and read
    back, as many cameras and data sets store their frames: the 8 × 8 blocks' quantisation
    removes fine detail and adds its own."""
    import cv2

    def jpeg(image: Tensor) -> Tensor:
        a = image.to(torch.float32).clamp(0, 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        colour = a.shape[-1] == 3
        ok, data = cv2.imencode(".jpg", a[..., ::-1] if colour else a[..., 0], [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError(f"OpenCV could not encode a frame as JPEG at quality {quality}")
        b = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        b = b[..., ::-1] if colour else b[..., None]
        return torch.from_numpy(np.ascontiguousarray(b)).permute(2, 0, 1).to(image.dtype)

    return {**pair, "image1": jpeg(pair["image1"]), "image2": jpeg(pair["image2"])}


def cropped(pair: dict, top: int, bottom: int, left: int, right: int) -> dict:
    """``pair`` cut to its window without ``top``, ``bottom``, ``left`` and ``right`` pixels at
    those sides (the sky, the bonnet, a network's input crop): the frames, the road, the
    ground-truth flow and its valid pixels sliced, the camera's principal point moved
    (:meth:`Camera.cropped`); the motion is the same. A window that leaves nothing of the frame,
    or none of the road polygon, is an :class:`UnfitOption` naming ``--crop``."""
    rows, cols = pair["image1"].shape[-2:]
    if top + bottom >= rows or left + right >= cols:
        raise UnfitOption(f"--crop: {top} + {bottom} rows or {left} + {right} columns leave nothing of a "
                          f"{rows} x {cols} frame")
    window = (..., slice(top, rows - bottom), slice(left, cols - right))
    if not bool(pair["road"][window].any()):  # (the figures are over the road: each would read 0 over no pixel)
        raise UnfitOption(f"--crop: the window of rows {top} to {rows - bottom - 1} and columns {left} to "
                          f"{cols - right - 1} of a {rows} x {cols} frame holds none of the road polygon")
    out = {**pair, "camera": pair["camera"].cropped(left, top, right, bottom)}
    for key in ("image1", "image2", "road", "valid", "flow"):
        if pair.get(key) is not None:
            out[key] = pair[key][window].contiguous()
    return out


def resized(pair: dict, factor: float) -> dict:
    """``pair`` as a camera of ``factor`` times the resolution records it (a network run on smaller
    frames): both frames resized by OpenCV's area interpolation and rounded to 8 bits, the road
    where it covers at least half of a new pixel, the camera scaled (:meth:`Camera.scaled`), and
    the ground-truth flow, where there is any, averaged over each new pixel's valid old ones and
    scaled (valid where at least half of them are): the road's flow is smooth, so its mean over
    a pixel is its value at the pixel's centre to first order."""
    import cv2

    rows, cols = pair["image1"].shape[-2:]
    h, w = max(1, round(rows * factor)), max(1, round(cols * factor))

    def area(x: Tensor) -> Tensor:  # (C, H, W) -> (C, h, w) float32
        a = x.to(torch.float32).permute(1, 2, 0).contiguous().numpy()
        return torch.from_numpy(cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA).reshape(h, w, -1)).permute(2, 0, 1)

    out = {**pair, "camera": pair["camera"].scaled(w / cols, h / rows)}
    for key in ("image1", "image2"):
        out[key] = area(pair[key]).clamp(0, 255).round().to(pair[key].dtype).contiguous()
    out["road"] = area(pair["road"]) >= 0.5
    if pair.get("flow") is not None:
        share = area(pair["valid"])
        total = area(pair["flow"].to(torch.float32) * pair["valid"])
        mean = total / share.clamp_min(1e-6)
        out["flow"] = torch.stack([mean[0] * (w / cols), mean[1] * (h / rows)]).to(pair["flow"].dtype).contiguous()
        out["valid"] = share >= 0.5
    return out


def measure(name: str, pairs: list[tuple[str, Callable[[], dict]]], methods: dict, progress: bool) -> dict:
    """Every pair of a data set through :func:`run_pair`; the summary rows and the per-pair results."""
    from fsof_torch.io.progress import progress_bar

    per_pair = []
    for i, (pair_name, load) in enumerate(progress_bar(pairs, enabled=progress, desc=name, unit="pair")):
        pair = {**load(), "name": pair_name}
        if i == 0:
            run_pair(pair, methods)  # once untimed: first calls load code and allocate
        per_pair.append({"pair": pair_name, **run_pair(pair, methods)})
    results = [{k: v for k, v in r.items() if k != "pair"} for r in per_pair]
    return {"rows": summarize(results), "pairs": per_pair}


def step_list(text: str) -> list[int]:
    """``--steps``: comma-separated whole numbers >= 0, at least one (argparse's type)."""
    try:
        steps = [int(k) for k in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected whole numbers >= 0 separated by commas, got {text!r}") from None
    if any(k < 0 for k in steps) or not any(steps):
        raise argparse.ArgumentTypeError(f"expected whole numbers >= 0, not all 0, got {text!r}")
    return steps


def main(argv: list[str] | None = None) -> int:
    from cli import json_object

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA,
                        help="folder holding kitti15_000000/ and kitti_odometry_straight/ (default: ../shared/data)")
    parser.add_argument("--pair", type=Path, metavar="DIR",
                        help="another KITTI 2015 pair in kitti15_000000's layout (image_10.png, image_11.png, "
                             "calib_cam_to_cam.txt, road.json; flow_noc_10.png where there is ground truth), "
                             "instead of --data's")
    parser.add_argument("--clip", type=Path, metavar="DIR",
                        help="another KITTI odometry clip in kitti_odometry_straight's layout (image_l/, calib.txt, "
                             "road.json; poses.txt where there are poses), instead of --data's")
    parser.add_argument("--pairs", type=int, default=None, help="only the first N pairs of the clip")
    parser.add_argument("--no-ecc", action="store_true", help="leave out the ECC homography")
    parser.add_argument("--no-sequence", action="store_true", help="leave out the clip's fit_sequence method")
    parser.add_argument("--height", type=float, default=1.65, help="camera height, m (default 1.65)")
    parser.add_argument("--pitch-deg", type=float, default=0.0,
                        help="the clip's camera pitch for the refiner, degrees (default 0: the calibration has none)")
    parser.add_argument("--roll-deg", type=float, default=0.0,
                        help="the camera roll for the refiner on both data sets, degrees (default 0: the "
                             "calibration has none); as --pitch-deg, it also tilts the axes of the turns that "
                             "--yaw-deg, --pitch-change-deg and --roll-change-deg simulate")
    parser.add_argument("--step", type=int, default=1,
                        help="clip pairs this many frames apart, every step-th frame, at most the clip's frames "
                             "less one (default 1; 3: about 130 km/h at 10 Hz instead of 43)")
    parser.add_argument("--steps", type=step_list, default=None, metavar="K,K,...",
                        help="instead of --step: clip pairs whose frames are these many apart in turn, from "
                             "frame 0 (e.g. 1,1,2,2,3: a car speeding up; 0: a frame repeated, a stop)")
    parser.add_argument("--yaw-deg", type=float, default=0.0,
                        help="turn every pair by this many degrees of yaw (image 2 resampled; default 0)")
    parser.add_argument("--slalom", type=float, nargs=2, default=None, metavar=("AMPLITUDE_DEG", "PERIOD"),
                        help="the clip seen by a camera that also yaws back and forth: frame k turned to "
                             "AMPLITUDE_DEG sin(2 pi k / PERIOD) degrees about the road's normal, every frame cut "
                             "to one window (a clip still: fit_sequence runs; the KITTI pair as given)")
    parser.add_argument("--pitch-change-deg", type=float, default=0.0,
                        help="pitch every pair's camera by this many degrees between the frames (default 0)")
    parser.add_argument("--roll-change-deg", type=float, default=0.0,
                        help="roll every pair's camera by this many degrees between the frames (default 0)")
    parser.add_argument("--resize", type=float, default=1.0, metavar="FACTOR",
                        help="resize every frame by this factor first (area interpolation; ground truth "
                             "averaged; default 1)")
    parser.add_argument("--exposure-gain", type=float, default=1.0,
                        help="make every pair's image 2 this many times as bright (clipped to 0..255; default 1)")
    parser.add_argument("--reverse", action="store_true",
                        help="swap every pair's frames, and take the clip's pairs last to first: the backward "
                             "flow, or the street driven in reverse (no ground-truth flow then)")
    parser.add_argument("--mirror", action="store_true",
                        help="mirror every pair left to right first (frames, road, ground truth, camera, poses): "
                             "the street seen from its other side")
    parser.add_argument("--jpeg", type=int, default=None, metavar="QUALITY",
                        help="store every frame as JPEG at this quality (1..100) and read it back first (default: "
                             "as given)")
    parser.add_argument("--crop", type=int, nargs=4, default=(0, 0, 0, 0), metavar=("TOP", "BOTTOM", "LEFT", "RIGHT"),
                        help="cut every pair to the window without so many pixels at each side first (the sky, the "
                             "bonnet; default 0 0 0 0)")
    parser.add_argument("--mask-grow", type=int, default=0, metavar="PX",
                        help=f"give the methods the road polygon grown by PX pixels (negative: shrunk; at most "
                             f"{MAX_GROW} either way), as a loose road mask; the figures stay over the polygon "
                             f"(default 0)")
    parser.add_argument("--odometry-error", nargs=2, type=float, default=(1.0, 0.0), metavar=("SCALE", "YAW_DEG"),
                        help="make the poses' odometry wrong as wheel odometry is: its translation SCALE times as "
                             "long, its yaw YAW_DEG degrees a frame more (default 1 0: as measured)")
    parser.add_argument("--no-turn-screen", action="store_true",
                        help="also run the refiner without its screen of turns (turn_starts=()), and both "
                             "without the start from DIS's flow (flow_start=False)")
    parser.add_argument("--no-prior-retry", action="store_true",
                        help="also run the refiner without its retry without the coarsest level's prior "
                             "(retry_without_prior=False)")
    parser.add_argument("--no-reverse-screen", action="store_true",
                        help="also run the refiner without its screen of steps backwards (reverse_starts=())")
    parser.add_argument("--estimator", type=json_object, action="append", default=[], metavar="OPTIONS",
                        help="add a row: the refiner with ImageMotionEstimator(**OPTIONS), a JSON object "
                             "(repeatable), e.g. '{\"smooth_sigma\": 0.7}'")
    parser.add_argument("--json", type=Path,
                        help="write every number (per pair too; the options and fit_sequence's mounting too) here; "
                             "an earlier file there is removed at the start")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    if args.pairs is not None and args.pairs < 1:
        parser.error(f"--pairs: expected >= 1, got {args.pairs}")
    if args.step < 1:
        parser.error(f"--step: expected >= 1, got {args.step}")
    if args.steps is not None and args.step != 1:
        parser.error("--steps: give --step or --steps, not both")
    if not (math.isfinite(args.height) and args.height > 0):
        parser.error(f"--height: expected a positive height in m, got {args.height}")
    if not (math.isfinite(args.pitch_deg) and abs(args.pitch_deg) < 45):
        parser.error(f"--pitch-deg: expected a number of degrees within (-45, 45), got {args.pitch_deg}")
    if not (math.isfinite(args.roll_deg) and abs(args.roll_deg) < 45):
        parser.error(f"--roll-deg: expected a number of degrees within (-45, 45), got {args.roll_deg}")
    import cv2

    if not args.no_ecc and not hasattr(cv2, "findTransformECCWithMask"):
        parser.error(f"the ECC homography needs OpenCV >= 4.13 (cv2.findTransformECCWithMask), got "
                     f"{cv2.__version__}: upgrade opencv-python-headless or pass --no-ecc")
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    methods = {k: v for k, v in METHODS.items() if not (args.no_ecc and k == "ECC homography")}
    extra = {**(TURN_ROWS if args.no_turn_screen else {}), **(PRIOR_ROWS if args.no_prior_retry else {}),
             **(REVERSE_ROWS if args.no_reverse_screen else {})}
    from fsof_torch import ImageMotionEstimator

    for options in args.estimator:  # (checked before any work: a bad name or value exits 2)
        try:
            ImageMotionEstimator(**options)
        except (TypeError, ValueError) as err:
            parser.error(f"--estimator: {json.dumps(options)}: {err}")
        extra[f"refiner, {json.dumps(options)}"] = options
    for name, options in extra.items():
        methods[name] = (None, lambda pair, dis, options=options: refiner_flow(pair, dis, **options))
    turn = (args.yaw_deg, args.pitch_change_deg, args.roll_change_deg)
    for name, value in zip(("--yaw-deg", "--pitch-change-deg", "--roll-change-deg"), turn):
        if not math.isfinite(value) or abs(value) >= 45:
            parser.error(f"{name}: expected a number of degrees within (-45, 45), got {value}")
    if args.slalom is not None:
        amplitude, period = args.slalom
        if not (math.isfinite(amplitude) and 0 < amplitude <= 20):
            parser.error(f"--slalom: expected an amplitude within (0, 20] degrees, got {amplitude}")
        if not (math.isfinite(period) and period > 2):
            # (a period of 2 frames samples the sine at its zeros: no frame would turn)
            parser.error(f"--slalom: expected a period of more than 2 frames (2 turns no frame), got {period}")
    if not (math.isfinite(args.exposure_gain) and 0.1 <= args.exposure_gain <= 10):
        parser.error(f"--exposure-gain: expected a factor within [0.1, 10], got {args.exposure_gain}")
    if args.jpeg is not None and not 1 <= args.jpeg <= 100:
        parser.error(f"--jpeg: expected a quality within [1, 100], got {args.jpeg}")
    if min(args.crop) < 0:
        parser.error(f"--crop: expected pixels >= 0 at each side, got {' '.join(map(str, args.crop))}")
    if abs(args.mask_grow) > MAX_GROW:
        parser.error(f"--mask-grow: expected at most {MAX_GROW} pixels either way, got {args.mask_grow}")
    if not (math.isfinite(args.resize) and 0.1 <= args.resize <= 1):
        parser.error(f"--resize: expected a factor within [0.1, 1], got {args.resize}")
    from cli import odometry_error

    scale, yaw_error = odometry_error(parser, args.odometry_error)
    need = {"kitti15": ("image_10.png", "image_11.png", "calib_cam_to_cam.txt", "road.json"),
            "clip": ("image_l", "calib.txt", "road.json")}
    if args.pair is None and args.clip is None:
        folders = {"kitti15": args.data / "kitti15_000000", "clip": args.data / "kitti_odometry_straight"}
        if not any(root.is_dir() for root in folders.values()):
            print(f"error: --data: no kitti15_000000/ or kitti_odometry_straight/ in {str(args.data)!r}",
                  file=sys.stderr)
            return 2
        option_of = {key: "--data" for key in folders}
    else:
        folders = {k: v for k, v in (("kitti15", args.pair), ("clip", args.clip)) if v is not None}
        option_of = {"kitti15": "--pair", "clip": "--clip"}
    for key, root in folders.items():
        missing = [n for n in need[key] if not (root / n).exists()]
        if missing and (root.is_dir() or option_of[key] != "--data"):  # (--data may lack one sample)
            print(f"error: {option_of[key]}: {str(root)!r} lacks {', '.join(missing)} (the figures are over the road "
                  f"polygon of road.json)", file=sys.stderr)
            return 2
    frames = clip_frames(folders.get("clip"))
    if frames is not None and args.steps is not None and sum(args.steps) >= frames:
        parser.error(f"--steps: expected frames at most {frames - 1} apart in all (the clip {str(folders['clip'])!r} "
                     f"has {frames} frames), got {sum(args.steps)}")
    if frames is not None and args.step >= frames:
        parser.error(f"--step: expected at most {frames - 1} (the clip {str(folders['clip'])!r} has {frames} "
                     f"frames), got {args.step}")
    from cli import json_path, write_json

    inputs = {"--data": args.data} if args.pair is None and args.clip is None else {"--pair": args.pair,
                                                                                    "--clip": args.clip}
    args.json = json_path(parser, args.json, inputs)
    report: dict[str, Any] = {"threads": 1, "opencv": cv2.__version__, "torch": torch.__version__, "step": args.step,
                              "yaw_deg": args.yaw_deg, "pitch_change_deg": args.pitch_change_deg,
                              "roll_change_deg": args.roll_change_deg, "exposure_gain": args.exposure_gain,
                              "resize": args.resize, "reverse": args.reverse, "mask_grow": args.mask_grow,
                              "mirror": args.mirror, "crop": list(args.crop), "jpeg": args.jpeg,
                              "odometry_error": [scale, yaw_error], "slalom": args.slalom, "steps": args.steps,
                              "options": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}}
    def transformed(data: list[tuple[str, Callable[[], dict]]], clip: bool) -> list[tuple[str, Callable[[], dict]]]:
        """The data set's pairs as the options change them (each loaded when called)."""
        if args.slalom is not None and clip:  # (first: each frame by its place in the clip)
            first = data[0][1]()
            window = slalom_window(first["camera"], tuple(first["image1"].shape[-2:]), clip_frames(folders["clip"]),
                                   *args.slalom)
            data = [(name, lambda load=load: slalomed(load(), *args.slalom, window)) for name, load in data]
        if args.reverse:  # (last to first: image 2 of a pair is image 1 of the next, a clip to fit)
            data = [(name, lambda load=load: reversed_pair(load())) for name, load in data[::-1]]
        if args.mirror:
            data = [(name, lambda load=load: mirrored(load())) for name, load in data]
        if any(args.crop):
            data = [(name, lambda load=load: cropped(load(), *args.crop)) for name, load in data]
        if args.resize != 1.0:
            data = [(name, lambda load=load: resized(load(), args.resize)) for name, load in data]
        if any(turn):
            data = [(name, lambda load=load: turned_by_options(load(), turn)) for name, load in data]
        if args.exposure_gain != 1.0:
            data = [(name, lambda load=load: exposed(load(), args.exposure_gain)) for name, load in data]
        if args.jpeg is not None:  # (after the frames are formed: what a camera stores)
            data = [(name, lambda load=load: compressed(load(), args.jpeg)) for name, load in data]
        if args.mask_grow:  # (last: the polygon as resized or turned)
            data = [(name, lambda load=load: grown(load(), args.mask_grow)) for name, load in data]
        if (scale, yaw_error) != (1.0, 0.0):
            data = [(name, lambda load=load: {**load(), "odometry_error": (scale, yaw_error)}) for name, load in data]
        return data

    loaders = (("kitti15", lambda root: kitti15(root, args.height, args.roll_deg)),
               ("clip", lambda root: odometry_clip(root, args.height, args.pitch_deg, args.step,
                                                   args.roll_deg, steps=args.steps)[:args.pairs]))
    try:  # (a folder the library cannot read, or an option its frames cannot take, is refused before any
        # work, by one pair of each data set: a clip's later frames are read as it runs)
        datasets = {key: transformed(checked_data(option_of[key], lambda root=folders[key], read=pairs: read(root)),
                                     key == "clip")
                    for key, pairs in loaders if folders.get(key) is not None and folders[key].is_dir()}
        for data in datasets.values():
            data[0][1]()
    except UnfitOption as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for key, _ in loaders:
        root = folders.get(key)
        if root is None:
            continue
        if key == "kitti15":
            truth = ("ground truth: road EPE over road ∩ valid"
                     if (root / "flow_noc_10.png").is_file() and not args.reverse else "no ground-truth flow")
            title = f"KITTI 2015 pair {root.resolve().name} ({truth})"
        else:
            posed = "" if (root / "poses.txt").is_file() else "no poses, "
            title = f"KITTI odometry clip {root.resolve().name} ({posed}" \
                    f"no ground-truth flow)"
        if not root.is_dir():
            print(f"{title}: {root} not found, skipped", file=sys.stderr)
            continue
        data, run_methods = datasets[key], dict(methods)
        # (turned or exposed, image 2 of a pair is not image 1 of the next: no clip to fit)
        changed = any(turn) or args.exposure_gain != 1.0
        mounting = None
        try:  # (a later frame the library cannot read: the same error, no traceback)
            if key == "clip" and not args.no_sequence and not changed and len(data) > 1:
                name, method, mounting = clip_method(data, not args.no_progress)
                run_methods[name] = (None, method)
            result = measure(key, data, run_methods, not args.no_progress)
        except UnfitData as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        if mounting is not None:
            result["mounting"] = mounting  # (fit_sequence's calibration, as printed)
        report[key] = result
        step = f", frames {args.step} apart" if key == "clip" and args.step > 1 else ""
        if key == "clip" and args.steps is not None:
            step += f", frames {','.join(map(str, args.steps))} apart in turn"
        if args.reverse:
            step += ", frames swapped (the backward flow)"
        if args.mask_grow:
            step += f", the methods given the polygon {'grown' if args.mask_grow > 0 else 'shrunk'} by " \
                    f"{abs(args.mask_grow)} px"
        if args.mirror:
            step += ", mirrored left to right"
        if args.jpeg is not None:
            step += f", stored as JPEG at quality {args.jpeg}"
        if any(args.crop):
            step += ", cut by {} / {} / {} / {} px at the top / bottom / left / right".format(*args.crop)
        if args.slalom is not None and key == "clip":
            step += ", the camera yawing back and forth by {:g}° over {:g} frames".format(*args.slalom)
        turns = ", ".join(f"{v:g}° of {n}" for v, n in zip(turn, ("yaw", "pitch", "roll")) if v)
        gain = f", image 2 {args.exposure_gain:g} times as bright" if args.exposure_gain != 1.0 else ""
        if args.resize != 1.0:
            gain += f", resized by {args.resize:g} (EPE in its pixels)"
        if (scale, yaw_error) != (1.0, 0.0) and key == "clip":
            gain += f", odometry's steps {scale:g} times as long and its yaw {yaw_error:+g}° a frame off"
        print(f"\n{title}: {len(result['pairs'])} pair(s){step}{', turned by ' + turns if turns else ''}{gain}\n")
        print(table(result["rows"]))
        disagreement = images_against_poses(result["pairs"])
        if disagreement is not None:
            print("\n" + disagreement)
    print(f"\nOne thread (torch and OpenCV); OpenCV {cv2.__version__}, torch {torch.__version__}. Means over the "
          f"pairs. 'CPU s / pair': the process's CPU time, for ECC and the refiner on top of DIS.")
    if args.json is not None:
        write_json(args.json, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
