"""Auto road (fsof_torch.detect_road): quality on synthetic scenes and the shared real data, and time.

Prints five tables (six with ``--turns``), single thread (the first two from the synthetic presets):

1. Synthetic presets (default, body-motion, crest, dip; pairs 0, 10, 20, 30 at 375 x 1242): IoU,
   precision and recall against the scene's true road, mean and min per preset, and the flags;
   the IoU with ``edges=False`` (the windows' own boundary, for the refit and the result); and the
   IoU when the scene's exact road motion is given (what the judging alone achieves). Below it, the
   true road split by what image 2 shows of it (``road_parts``: seen there, near the road's edge
   or inside; occluded there; or out of its view), each part's share and the recall on it with
   the estimated and the exact motion: two frames give the last two parts no evidence of their own.
2. Real KITTI: the shared pair 000000, the same pair through the 16 windows 4 pixels smaller than
   the frame at offsets 0-3 from its top and left (``image_fit_settings.crops``: one frame's
   figures are one draw of the fits' points), and every pair of the 51-frame straight clip.
   road.json is a conservative polygon (the clip's: the ego lane only), so the figures are the
   share of the auto mask inside the polygon and the share of the polygon the mask covers; mean
   and min over the pairs, the number of empty and of flagged masks; the same with ``edges=False``
   (the windows' own boundary, for the refit and the result). Beside it, for reference,
   the flow-based detection of earlier versions (fsof_torch.detect_freespace on OpenCV DIS flow,
   as the refine job called it; flagged where its success is false).
3. Time per pair at 1242 x 375 (the shared KITTI pair): the detection with its own motion
   estimates (on the seed at half size, again on the road), the detection judging a motion it is
   given (what it adds to a refiner that estimated the motion anyway; also with ``edges=False``:
   what following the edges costs), the default image motion
   estimate on a given mask (the refiner's own estimation), and refine_flow on DIS flow with
   mask="auto" against the same with the polygon as mask; medians of --repeat runs.

4. Driving slowly (synthetic, pairs 0, 6, 12 at 375 x 1242): the default scene at 2 to 5 m/s at
   10 Hz and the CARLA-like sharp turn (6 m/s at 20 Hz, 0.3 m a frame), where a 0.3 m step's
   parallax sinks below what the images show. Per speed: the flags and the step the evidence had
   to show (``stats["max_height_m"]``), the IoU, and the road end-point error (px, over the true
   road) of DIS and of ``refine_flow(DIS, "auto", images)``, with the default and with
   ``slow_max_height_m=None`` (the step kept at max_height_m: such pairs are flagged and left
   unrefined).

5. With ``--turns``, sharp turns (synthetic): the default scene driven through turns of radius
   13 to 54 m, the detection (its seed along the vehicle's path where the motion found turns the
   path out of the straight seed) against ``follow_path=False`` (the seed straight ahead only):
   the flags, the IoU with the true road, the seed's agreement and the time.

With ``--yaw-deg D`` (``--pitch-change-deg``, ``--roll-change-deg``) the real pairs of tables 2 and 3
are seen as by a camera that also turns between the frames (``real_road.turned``: image 2
resampled through the rotation's homography, both frames and the polygon cropped to where it is
defined): the real street's texture in a turn of known motion. With ``--reverse`` the real pairs'
frames are swapped (before any turn): the road recedes, as when reversing or in the backward flow;
the polygon stays the forward pair's.

The clip's frames are taken as the library reads them: a grey camera's (KITTI odometry's
``image_0``) in its one channel, a colour camera's in colour, as the pair's. Samples the library
cannot read (a calibration without the camera, frames of another size than its ``S_rect`` or
than each other, a malformed road.json) exit 2 naming ``--data``, before any work.

Run: python benchmarks/auto_road.py [--data ../shared/data] [--repeat 3] [--no-synthetic] [--no-slow] [--no-real]
     [--pairs 0 10 20 30]
     [--yaw-deg D] [--pitch-change-deg D] [--roll-change-deg D] [--reverse] [--turns]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import warnings
from pathlib import Path

import torch

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data"
PRESETS = ("default", "body-motion", "crest", "dip")
PAIRS = (0, 10, 20, 30)
KITTI15 = ("kitti15_000000", ("image_10.png", "image_11.png", "calib_cam_to_cam.txt", "road.json"))
CLIP = ("kitti_odometry_straight", ("image_l", "calib.txt", "road.json"))


def dis(image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
    """OpenCV DIS (medium) on luma grey images, as the refine job computes it: (1, 2, H, W) from
    (1, 3, H, W) RGB or (1, 1, H, W) grey images."""
    from refine.sources import dis_flow

    rgb = [im[0].expand(3, -1, -1) for im in (image1, image2)]
    return dis_flow(*rgb)[None]


PARTS = ("seen, near its edge", "seen, inside", "occluded", "out of view")


def edge_reach(level: int) -> int:
    """How far (pixels of the images) the detection's step 5 moves the road's boundary inwards onto
    image 1's edges at its working ``level``: ``height_window // 2 + 1`` pixels there (16 at KITTI's
    size; outwards one pixel of that level more)."""
    import inspect

    from fsof_torch import detect_road

    return (inspect.signature(detect_road).parameters["height_window"].default // 2 + 1) * 2 ** level


def road_parts(pair: dict, edge_px: int) -> dict[str, torch.Tensor]:
    """The true road of a rendered pair (``render_pair``'s dict) split by what image 2 shows of
    it, (1, 1, H, W) bool each, in :data:`PARTS`' order: seen in image 2 (its point visible there:
    ``valid``), within ``edge_px`` pixels (a square's half side) of what is not road in image 1 or
    of road hidden in image 2, or farther inside; ``"occluded"`` (the flow lands inside image 2 but
    the point is hidden there, behind a car); ``"out of view"`` (the flow takes it outside image 2:
    near the vehicle, or past the frame's side). Two frames give the last two no evidence of their
    own."""
    import cv2
    import numpy as np

    road, valid, flow = pair["road"].bool(), pair["valid"].bool(), pair["flow"]
    H, W = road.shape[-2:]
    road, valid = road.reshape(H, W), valid.reshape(H, W)
    x = torch.arange(W, dtype=flow.dtype) + flow[0]
    y = torch.arange(H, dtype=flow.dtype).reshape(H, 1) + flow[1]
    inside = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    occluded = road & ~valid & inside
    edge = (~road | occluded).numpy().astype(np.uint8)
    near = torch.from_numpy(cv2.dilate(edge, np.ones((2 * edge_px + 1,) * 2, np.uint8)) > 0)
    seen = road & valid
    parts = (seen & near, seen & ~near, occluded, road & ~valid & ~inside)
    return {k: v.reshape(1, 1, H, W) for k, v in zip(PARTS, parts)}


def synthetic_table(pairs: tuple[int, ...] = PAIRS) -> None:
    from fsof_torch import detect_road, render_pair

    print("Synthetic scenes, 375 x 1242, pairs " + ", ".join(map(str, pairs)))
    print("(exact motion: the scene's own road motion given, nothing estimated)")
    print(f"{'preset':>12} {'IoU mean':>9} {'IoU min':>8} {'precision':>10} {'recall':>7} "
          f"{'edges=False: IoU mean':>22} {'exact motion: IoU mean':>23} {'min':>6}  flags")
    # per preset: the true road's pixels in each part, and those the detections found
    shares = {}
    for preset in PRESETS:
        ious, precisions, recalls, plain, exact, flags = [], [], [], [], [], []
        counts = {k: torch.zeros(3, dtype=torch.float64) for k in PARTS}  # (true, found, found exact)
        for index in pairs:
            p = render_pair(preset, index)
            t = p["road"][None].bool()
            det = detect_road(p["image1"][None], p["image2"][None], p["camera"])
            m = det.mask
            ious.append(float((m & t).sum() / (m | t).sum()))
            precisions.append(float((m & t).sum() / m.sum().clamp_min(1)))
            recalls.append(float((m & t).sum() / t.sum()))
            flags += det.flag
            plain_mask = detect_road(p["image1"][None], p["image2"][None], p["camera"], edges=False).mask
            plain.append(float((plain_mask & t).sum() / (plain_mask | t).sum()))
            motion = {"model": "plane", **{k: v for k, v in p["plane"].items() if k != "height"}}
            cam = p["camera"].replace(height=p["plane"]["height"])
            m_exact = detect_road(p["image1"][None], p["image2"][None], cam, motion=motion).mask
            exact.append(float((m_exact & t).sum() / (m_exact | t).sum()))
            for k, part in road_parts(p, edge_reach(det.level)).items():
                counts[k] += torch.tensor([part.sum(), (part & m).sum(), (part & m_exact).sum()], dtype=torch.float64)
        shares[preset] = counts
        tally = {f: flags.count(f) for f in sorted(set(flags))}
        print(f"{preset:>12} {statistics.mean(ious):9.3f} {min(ious):8.3f} {statistics.mean(precisions):10.3f} "
              f"{statistics.mean(recalls):7.3f} {statistics.mean(plain):22.3f} {statistics.mean(exact):23.3f} "
              f"{min(exact):6.3f}  {tally}")
    print("\nThe true road by what image 2 shows of it (pooled over the pairs): each part's share of the"
          "\nroad, and the recall on it, estimated motion / exact motion")
    print(f"{'preset':>12} " + " ".join(f"{k + ': share':>26} {'recall':>13}" for k in PARTS))
    for preset, counts in shares.items():
        total = sum(float(c[0]) for c in counts.values())
        cells = []
        for k in PARTS:
            n, found, found_exact = counts[k].tolist()
            recall = f"{found / n:.3f} / {found_exact / n:.3f}" if n else "-"
            cells.append(f"{n / total:26.3f} {recall:>13}")
        print(f"{preset:>12} " + " ".join(cells))


#: the sharp turns of docs/auto-road.md's Limits: (steering in rad of the default scene at 12 m/s, pair)
TURNS = ((-0.2, 10), (-0.1, 10), (-0.1, 30), (-0.05, 25), (0.05, 15), (0.1, 20), (0.2, 10))


def turns_table(cases: tuple[tuple[float, int], ...] = TURNS, size: tuple[int, int] | None = None) -> None:
    """The default scene driven through turns: the detection (its seed along the path where the
    motion turns the path out of the straight seed) against ``follow_path=False`` (the seed straight
    ahead only): flag, IoU with the true road, the seed's agreement, and time (median of 3)."""
    import time

    from fsof_torch import detect_road, render_pair

    print("\nSharp turns: the default scene at 12 m/s, 375 x 1242" if size is None else f"\nSharp turns, {size}")
    print(f"{'steering, pair':>15} {'flag':>12} {'IoU':>6} {'agreement':>9} {'ms':>7}   "
          f"{'follow_path=False: flag':>24} {'IoU':>6} {'agreement':>9} {'ms':>7}")
    ious = {True: [], False: []}
    for steering, index in cases:
        p = render_pair("default", index, steering=steering, **({} if size is None else {"size": size}))
        truth = p["road"][None].bool()
        cells = []
        for follow in (True, False):
            times = []
            for _ in range(3):
                t = time.perf_counter()
                det = detect_road(p["image1"][None], p["image2"][None], p["camera"], follow_path=follow)
                times.append(time.perf_counter() - t)
            iou = float((det.mask & truth).sum() / (det.mask | truth).sum())
            ious[follow].append(iou)
            cells.append(f"{det.flag[0]:>{24 if not follow else 12}} {iou:6.3f} {float(det.seed_agreement[0]):9.2f} "
                         f"{1e3 * statistics.median(times):7.1f}")
        print(f"{steering:+6.2f}, {index:6d} " + "   ".join(cells))
    print(f"{'mean IoU':>15} {statistics.mean(ious[True]):19.3f} {'':17}   {statistics.mean(ious[False]):31.3f}")


SLOW = (("default", 2.0), ("default", 3.0), ("default", 4.0), ("default", 5.0), ("carla-turning", None))


def slow_table() -> None:
    from fsof_torch import refine_flow, render_pair

    print("\nDriving slowly: synthetic pairs 0, 6, 12 at 375 x 1242, DIS refined with mask='auto'")
    print("(road EPE in px over the true road, pooled; 'fixed step': slow_max_height_m=None)")
    print(f"{'scene':>22} {'m/frame':>8} {'step m':>11} {'IoU':>6} {'DIS':>6} {'refined':>8}  flags"
          f"{'':14} | fixed step: {'refined':>8}  flags")
    for preset, speed in SLOW:
        overrides = {} if speed is None else {"speed": speed, "dt": 0.1}
        ious, steps, flags, flags_fixed, step_m = [], [], [], [], 0.0
        sums = torch.zeros(3, dtype=torch.float64)
        count = 0
        for index in (0, 6, 12):
            p = render_pair(preset, index, **overrides)
            t = p["road"][None].bool()
            images = (p["image1"][None], p["image2"][None])
            flow = dis(p["image1"][None], p["image2"][None])
            out = refine_flow(flow, "auto", p["camera"], images=images, warn=False)
            fixed = refine_flow(flow, "auto", p["camera"], images=images, warn=False,
                                road_options={"slow_max_height_m": None})
            use = (t & p["valid"][None])[0, 0]
            for i, f in enumerate((flow, out.flow, fixed.flow)):
                sums[i] += (f[0] - p["flow"]).norm(dim=0)[use].double().sum()
            count += int(use.sum())
            m = out.road.mask
            ious.append(float((m & t).sum() / (m | t).sum()))
            steps.append(float(out.road.stats["max_height_m"][0]))
            flags += out.road.flag
            flags_fixed += fixed.road.flag
            step_m = float(p["odometry"]["z_d"])
        e = (sums / max(count, 1)).tolist()
        name = f"{preset} {speed:g} m/s" if speed is not None else preset
        counts = str({f: flags.count(f) for f in sorted(set(flags))})
        counts_fixed = {f: flags_fixed.count(f) for f in sorted(set(flags_fixed))}
        print(f"{name:>22} {step_m:8.2f} {'/'.join(f'{h:g}' for h in steps):>11} {statistics.mean(ious):6.3f} "
              f"{e[0]:6.3f} {e[1]:8.3f}  {counts:<19} | {e[2]:20.3f}  {counts_fixed}")


def real_pairs(root: Path, turn: tuple[float, float, float] = (0.0, 0.0, 0.0), *, kitti15: bool = True,
               clip: bool = True, reverse: bool = False):
    """(name, image1, image2, camera, polygon mask) of the shared KITTI pair and the clip's pairs
    (those of the two asked for); with ``reverse``, each pair's frames swapped (the road receding:
    reversing, or the backward flow; the polygon stays the one drawn on the forward pair's image 1,
    as ``real_road.reversed_pair`` keeps it); with a ``turn`` (yaw, pitch change, roll change in
    degrees), image 2 as a camera that also turns so between the frames sees it, both frames and
    the polygon cropped to where it is defined (``real_road.turned``)."""
    from fsof_torch import Camera
    from fsof_torch.data.folders import list_images
    from fsof_torch.io import read_image, read_road_mask

    from image_fit_settings import crops
    from real_road import turned

    def view(name, im1, im2, camera, poly):
        if reverse:
            im1, im2 = im2, im1
        if not any(turn):
            return name, im1, im2, camera, poly
        t = turned({"image1": im1[0], "image2": im2[0], "road": poly[0], "camera": camera}, *turn)
        return name, t["image1"][None], t["image2"][None], t["camera"], t["road"][None]

    if kitti15:
        k15 = root / KITTI15[0]
        im1, im2 = (read_image(k15 / f"image_1{i}.png")[None] for i in (0, 1))
        camera = Camera.from_kitti(k15 / "calib_cam_to_cam.txt", cam=2, height=1.65)
        poly = read_road_mask(k15 / "road.json", tuple(im1.shape[-2:])).reshape(1, 1, *im1.shape[-2:]).bool()
        yield view("kitti15 pair", im1, im2, camera, poly)
        # the same pair through the 16 windows 4 px smaller: the same scene, other draws of the points
        for i, w in enumerate(crops({"camera": camera, "image1": im1, "image2": im2, "road": poly})):
            yield view(f"kitti15 windows {i:02d}", w["image1"], w["image2"], w["camera"], w["road"])
    if clip:
        folder = root / CLIP[0]
        cam = Camera.from_kitti(folder / "calib.txt", cam=0, height=1.65)
        files = list_images(folder / "image_l")  # (in frame order, as the library pairs them)
        frames = [one_channel_if_grey(read_image(f)[None]) for f in files]
        size = tuple(frames[0].shape[-2:])
        poly = read_road_mask(folder / "road.json", size).reshape(1, 1, *size).bool()
        for i in range(len(frames) - 1):
            yield view(f"straight clip {i:02d}", frames[i], frames[i + 1], cam, poly)


def one_channel_if_grey(image: torch.Tensor) -> torch.Tensor:
    """A frame (1, 3, H, W) as read (``read_image`` repeats a grey file's channel): its one channel
    where the three are equal (the straight clip's grey camera), else its colour, as the KITTI
    pair's frames are taken (never one colour channel of a colour clip)."""
    return image[:, :1] if bool((image == image[:, :1]).all()) else image


def unreadable(root: Path, kitti15: bool, clip: bool) -> str | None:
    """What of the real samples in ``root`` (those asked for) the library cannot read, as its
    datasets read them: the pair's frames against each other and the calibration's ``S_rect``, the
    clip's frames against each other (every one of them), each calibration's camera, each
    road.json (and a polygon that covers no pixel of its frames); None where all can be. Checked
    before any work: the tables read them later."""
    from fsof_torch.datasets import ImageFolderDataset, KittiSampleDataset
    from fsof_torch.io import read_road_mask

    roads = []
    try:
        if kitti15:
            pair = KittiSampleDataset(root / KITTI15[0], camera_height=1.65, ground_truth=False, road_json=False)[0]
            roads.append(read_road_mask(root / KITTI15[0] / "road.json", tuple(pair["image1"].shape[-2:])))
        if clip:
            folder = root / CLIP[0]
            frames = ImageFolderDataset(folder / "image_l", folder / "calib.txt", cam=0, ground_truth=False)
            for i in range(len(frames)):
                size = tuple(frames[i]["image1"].shape[-2:])
            roads.append(read_road_mask(folder / "road.json", size))
    except (ValueError, FileNotFoundError) as err:
        return str(err)
    for road in roads:  # (the tables' shares are of the polygon's pixels)
        if not bool(road.any()):
            return f"road.json: its road polygon covers no pixel of the {road.shape[-2]} x {road.shape[-1]} frames"
    return None


def real_table(root: Path, turn: tuple[float, float, float] = (0.0, 0.0, 0.0), *, kitti15: bool = True,
               clip: bool = True, reverse: bool = False) -> None:
    from fsof_torch import detect_freespace, detect_road

    rows: dict[str, dict[str, list]] = {}
    pixels = (0, 0)  # the KITTI pair: its polygon, and the auto road outside it
    for name, im1, im2, cam, poly in real_pairs(root, turn, kitti15=kitti15, clip=clip, reverse=reverse):
        group = name.rstrip("0123456789 ")
        flow = dis(im1, im2)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            det = detect_road(im1, im2, cam, flow=flow)
            plain = detect_road(im1, im2, cam, flow=flow, edges=False)
            # the flow-based detection (detect_freespace on DIS's flow), for comparison
            old = detect_freespace(flow.to(cam.dtype), cam, bottom_rows=max(1, im1.shape[-2] // 8), threshold=1.0,
                                   relative_threshold=0.1, return_details=True)
        for method, m, flag in (("auto road (images)", det.mask, det.flag[0]),
                                ("edges=False", plain.mask, plain.flag[0]),
                                ("flow-based (DIS)", old.freespace, "" if bool(old.success[0]) else "failed")):
            r = rows.setdefault(group, {}).setdefault(method, {"inside": [], "cover": [], "empty": 0, "flagged": 0})
            n = int(m.sum())
            r["inside"].append(float((m & poly).sum()) / max(n, 1))
            r["cover"].append(float((m & poly).sum() / poly.sum()))
            r["empty"] += n == 0
            r["flagged"] += flag not in ("", "ok")
            if name == "kitti15 pair" and method == "auto road (images)":
                pixels = (int(poly.sum()), int((m & ~poly).sum()))
    turned = (", frames swapped" if reverse else "") + (
        f", image 2 turned by yaw {turn[0]:g}°, pitch {turn[1]:g}°, roll {turn[2]:g}°" if any(turn) else "")
    print(f"\nReal KITTI{turned}: share of the mask inside road.json's polygon, share of the polygon covered")
    print(f"{'data':>15} {'method':>19} {'pairs':>5} {'inside mean':>11} {'inside min':>10} {'cover mean':>10} "
          f"{'cover min':>9} {'empty':>5} {'flagged':>7}")
    for group, methods in rows.items():
        for method, r in methods.items():
            print(f"{group:>15} {method:>19} {len(r['inside']):5d} {statistics.mean(r['inside']):11.3f} "
                  f"{min(r['inside']):10.3f} {statistics.mean(r['cover']):10.3f} {min(r['cover']):9.3f} "
                  f"{r['empty']:5d} {r['flagged']:7d}")
    if kitti15:
        print(f"kitti15 pair: the polygon holds {pixels[0]} pixels of the frame; the auto road has {pixels[1]} outside it")


def time_table(root: Path, repeat: int, turn: tuple[float, float, float] = (0.0, 0.0, 0.0),
               reverse: bool = False) -> None:
    from cli import median_ms
    from fsof_torch import detect_road, refine_flow
    from fsof_torch.refinement.estimators import ImageMotionEstimator

    name, im1, im2, cam, poly = next(real_pairs(root, turn, clip=False, reverse=reverse))
    flow = dis(im1, im2)
    motion = detect_road(im1, im2, cam, flow=flow).motion
    estimator = ImageMotionEstimator()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rows = {
            "detect_road, own motion (seed + road fit)": lambda: detect_road(im1, im2, cam, flow=flow),
            "detect_road, own motion, no refit": lambda: detect_road(im1, im2, cam, flow=flow, refit=False),
            "detect_road, motion given (the judging)": lambda: detect_road(im1, im2, cam, motion=motion),
            "the same, edges=False": lambda: detect_road(im1, im2, cam, motion=motion, edges=False),
            "reference: image motion estimate on the polygon": lambda: estimator(flow, poly, cam, images=(im1, im2)),
            "refine_flow(DIS, polygon, images)": lambda: refine_flow(flow, poly, cam, images=(im1, im2)),
            "refine_flow(DIS, 'auto', images)": lambda: refine_flow(flow, "auto", cam, images=(im1, im2)),
            "reference: OpenCV DIS medium": lambda: dis(im1, im2),
        }
        ms = {k: median_ms(f, repeat) for k, f in rows.items()}
    ref = ms["reference: image motion estimate on the polygon"]
    print(f"\nTime per pair, {name}, {tuple(im1.shape[-2:])}, one thread, median of {repeat}")
    print(f"{'':>50} {'ms':>8} {'/ estimate':>10}")
    for k, v in ms.items():
        print(f"{k:>50} {v:8.1f} {v / ref:10.2f}")


def main(argv=None) -> int:
    import cv2

    from cli import description, pair_index, positive_int, present, reads_data, samples_folder

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the folder that holds kitti15_000000/ and kitti_odometry_straight/, at least one "
                             "(default: ../shared/data beside the repository, where both may be absent)")
    parser.add_argument("--repeat", type=positive_int, default=3,
                        help="timed runs per row of the time table (default 3)")
    parser.add_argument("--no-synthetic", action="store_true", help="leave out the synthetic presets' table")
    parser.add_argument("--no-slow", action="store_true", help="leave out the table of driving slowly")
    parser.add_argument("--no-real", action="store_true", help="leave out the real-data tables")
    parser.add_argument("--turns", action="store_true",
                        help="also the table of sharp turns (the default scene through 7 turns; about a minute)")
    parser.add_argument("--pairs", type=pair_index, nargs="+", default=list(PAIRS),
                        help="the synthetic presets' pairs (default: 0 10 20 30; other pairs check that a "
                             "change helps beyond these)")
    parser.add_argument("--yaw-deg", type=float, default=0.0,
                        help="the real pairs' image 2 as seen by a camera also turned by this yaw (real_road.py's)")
    parser.add_argument("--pitch-change-deg", type=float, default=0.0, help="likewise, a pitch change")
    parser.add_argument("--roll-change-deg", type=float, default=0.0, help="likewise, a roll change")
    parser.add_argument("--reverse", action="store_true",
                        help="the real pairs' frames swapped: the road receding (reversing, or the backward "
                             "flow; real_road.py's); with a turn, swapped first")
    args = parser.parse_args(argv)
    turn = (args.yaw_deg, args.pitch_change_deg, args.roll_change_deg)
    for option, degrees in zip(("--yaw-deg", "--pitch-change-deg", "--roll-change-deg"), turn):
        if not (math.isfinite(degrees) and abs(degrees) <= 30):
            print(f"{option}: expected finite degrees within ±30, got {degrees}", file=sys.stderr)
            return 2
    reads = reads_data(parser, args.data, args.no_real, "--no-real")
    data = samples_folder(parser, args.data, DEFAULT, dict([KITTI15, CLIP])) if reads else None
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    kitti15 = clip = False
    if data is not None and data.is_dir():  # (what the real tables read, checked before any work)
        kitti15 = present(data / KITTI15[0], KITTI15[1], f"KITTI pair {KITTI15[0]}")
        clip = present(data / CLIP[0], CLIP[1], f"KITTI clip {CLIP[0]}")
        problem = unreadable(data, kitti15, clip)
        if problem is not None:
            parser.error(f"--data: {problem}")
        for sample in (("kitti15",) if kitti15 else ()) + (("clip",) if clip else ()):
            try:  # (each sample's first pair turned: a turn that leaves no window of it defined)
                next(real_pairs(data, turn, kitti15=sample == "kitti15", clip=sample == "clip"))
            except ValueError as err:
                parser.error(f"--yaw-deg, --pitch-change-deg, --roll-change-deg: {err} (the turned frames may lose "
                             f"at most a fifth of their rows at the top and at the bottom): turn less")
    if not args.no_synthetic:
        synthetic_table(tuple(args.pairs))
    if data is not None:
        if data.is_dir():
            if kitti15 or clip:
                real_table(data, turn, kitti15=kitti15, clip=clip, reverse=args.reverse)
            if kitti15:
                time_table(data, args.repeat, turn, args.reverse)
        else:
            print(f"\n{data} is absent: no real-data tables")
    if not args.no_slow:
        slow_table()
    if args.turns:
        turns_table()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
