"""Speed of the road-motion estimate from two KITTI frames (the shared clip's first pair, 1226 × 370),
one thread, beside OpenCV DIS
(MEDIUM) in the same run, and of the image operations the fit takes from OpenCV on the CPU
against their torch / kornia equivalents.

Rows (median and minimum of ``--repeats`` calls each, interleaved call by call):

- DIS (the reference), ``fit_image`` (the default ``"plane"`` fit), the default refiner with the
  images (estimation, model flow, gate, fusion), and the gate alone; ``fit_image`` also under
  ``torch.no_grad`` instead of the inference mode it runs in (the price of autograd's bookkeeping
  on its many small operations); the fit and the refiner also
  without the starts straight ahead (``forward_starts=()``), which find fast driving: their price;
  and both with ``max_points=10000`` (more points per level, steadier and on synthetic frames
  more accurate, ``image_fit_settings.py``) and with 20 000 points spread evenly
  (``max_points=20000, gradient_fraction=1.0``, the more accurate choice there) and at the finest
  level only (``fine_points=20000``): their price; and with each band's blur inside the road
  mask (``masked_band=True``), alone and in the setting measured for real cameras
  (``fine_points=20000, smooth_sigma=1.0, masked_band=True``);
- a Gaussian blur σ = 4 (the band-pass), the pyramid's decimation and the road mask's pyramid
  (a 3 × 3 erosion at every second pixel): OpenCV against kornia / torch (the fast paths
  ``gaussian_blur``, ``image_pyramid`` and the mask pyramid take on the CPU); and both frames
  converted to grey, in place into one tensor (``to_grey``, as the fit does) against kornia's
  ``rgb_to_grayscale`` and a concatenation; and the road mask's pixels found by NumPy's
  ``flatnonzero`` (``mask_pixels``, the CPU path of every sample of the mask's points) against
  torch's ``nonzero``.

    python benchmarks/bench_image_fit.py [--repeats 15] [--baseline REV] [--kitti15] [--data DIR]

With ``--baseline REV`` (a git revision, imported beside the current package by
``baseline.py``), the rows are instead ``fit_image`` and the default refiner of that revision and
of the current one, interleaved call by call, with their ratio.

Uses the shared KITTI clip's first pair when ``../shared`` is there (with ``--kitti15``, the
KITTI 2015 pair 000000 instead: 1242 × 375, a road polygon twice as large), else a synthetic pair.
A folder named by ``--data`` must hold the clip (with ``--kitti15``, the pair): no fallback there.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
KITTI15_FILES = ("image_10.png", "image_11.png", "calib_cam_to_cam.txt", "road.json")
CLIP_FILES = ("image_l", "road.json", "calib.txt")


def pair(data: Path = DATA, kitti15: bool = False):
    import fsof_torch as fs
    from fsof_torch.data.folders import list_images

    if kitti15:
        k15 = data / "kitti15_000000"
        im1, im2 = fs.read_image(k15 / KITTI15_FILES[0]), fs.read_image(k15 / KITTI15_FILES[1])
        road = fs.read_road_mask(k15 / "road.json", size=tuple(im1.shape[-2:]))
        return im1, im2, road, fs.Camera.from_kitti(k15 / KITTI15_FILES[2], cam=2, height=1.65), "KITTI 2015 pair 000000"
    clip = data / "kitti_odometry_straight"
    if all((clip / name).exists() for name in CLIP_FILES):
        files = list_images(clip / "image_l")  # (the first pair in the library's frame order)
        im1, im2 = fs.read_image(files[0]), fs.read_image(files[1])
        road = fs.read_road_mask(clip / "road.json", size=tuple(im1.shape[-2:]))
        return im1, im2, road, fs.Camera.from_kitti(clip / "calib.txt", cam=0, height=1.65), "KITTI clip pair 0"
    p = fs.render_pair("default", 0)
    return p["image1"], p["image2"], p["road"], p["camera"], "synthetic default pair 0"


def main(argv: list[str] | None = None) -> int:
    from cli import baseline_revision, data_folder, description, positive_int

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--repeats", type=positive_int, default=15, help="interleaved timed calls per row (default 15)")
    parser.add_argument("--baseline", metavar="REV",
                        help="time against this git revision instead (one with fit_image: 0cbcee8 or later)")
    parser.add_argument("--kitti15", action="store_true", help="the KITTI 2015 pair instead of the clip's first")
    parser.add_argument("--data", metavar="DIR", type=Path, default=None,
                        help="the folder holding kitti_odometry_straight/ (with --kitti15: kitti15_000000/); "
                             "default: ../shared/data beside the repository, and without the clip there, a "
                             "synthetic pair")
    args = parser.parse_args(argv)
    args.baseline = baseline_revision(parser, args.baseline)
    if args.kitti15:
        data = data_folder(parser, args.data, DATA)
        missing = [n for n in KITTI15_FILES if not (data / "kitti15_000000" / n).is_file()]
        if missing:
            parser.error(f"--kitti15: {data / 'kitti15_000000'} lacks {', '.join(missing)} (see --data)")
    else:
        data = data_folder(parser, args.data, DATA, tuple(f"kitti_odometry_straight/{n}" for n in CLIP_FILES))
    base = None
    if args.baseline:
        from baseline import load_baseline

        try:
            base = load_baseline(args.baseline)
        except Exception as err:  # noqa: BLE001 - any failure to import that revision is the option's
            parser.error(f"--baseline: cannot import revision {args.baseline!r}: {type(err).__name__}: {err}")
        if not hasattr(base, "fit_image"):
            parser.error(f"--baseline: revision {args.baseline!r} has no fit_image to time (it came with 0cbcee8)")
    import cv2
    from kornia.color import rgb_to_grayscale
    from kornia.filters import gaussian_blur2d

    import fsof_torch as fs
    from fsof_torch.estimation.pyramid import gaussian_blur, image_pyramid, mask_pyramid
    from fsof_torch.estimation.sampling import mask_pixels
    from fsof_torch.evaluation.photometric import to_grey
    from refine.sources import dis_flow

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    warnings.simplefilter("ignore")
    im1, im2, road, cam, what = pair(data, args.kitti15)
    I1, I2, M = im1[None], im2[None], road[None]
    flow = dis_flow(im1, im2)[None]
    if base is not None:
        against_baseline(base, args.baseline, args.repeats, I1, I2, M, cam, flow, what)
        return 0
    refiner = fs.FreespaceRefiner()
    ahead_off = fs.FreespaceRefiner(estimator=fs.ImageMotionEstimator(forward_starts=()))
    more_points = fs.FreespaceRefiner(estimator=fs.ImageMotionEstimator(max_points=10000))
    accurate = {"max_points": 20000, "gradient_fraction": 1.0}
    accurate_refiner = fs.FreespaceRefiner(estimator=fs.ImageMotionEstimator(**accurate))
    fine_refiner = fs.FreespaceRefiner(estimator=fs.ImageMotionEstimator(fine_points=20000))
    masked_refiner = fs.FreespaceRefiner(estimator=fs.ImageMotionEstimator(masked_band=True))
    real_camera = {"fine_points": 20000, "smooth_sigma": 1.0, "masked_band": True}
    real_camera_refiner = fs.FreespaceRefiner(estimator=fs.ImageMotionEstimator(**real_camera))
    out = refiner(flow, M, cam, images=(I1, I2))
    gate = fs.ImageGate()
    grey = torch.cat([I1.mean(1, keepdim=True), I2.mean(1, keepdim=True)], 1)
    k = 2 * int(np.ceil(3 * 4.0)) + 1
    taps = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0

    def grey_in_place():
        pair = I1.new_empty((1, 2, *I1.shape[-2:]))
        to_grey(I1, out=pair[:, :1])
        return to_grey(I2, out=pair[:, 1:])

    def torch_decimate(x):
        x = F.conv2d(F.pad(x.reshape(-1, 1, *x.shape[-2:]), (2, 2, 0, 0), mode="reflect"), taps.reshape(1, 1, 1, 5))
        x = F.conv2d(F.pad(x, (0, 0, 2, 2), mode="reflect"), taps.reshape(1, 1, 5, 1))
        return x[..., ::2, ::2]

    rows = {
        "DIS (MEDIUM), the reference": lambda: dis_flow(im1, im2),
        "fit_image (plane, defaults)": lambda: fs.fit_image(I1, I2, M, cam),
        "fit_image under torch.no_grad, not inference mode": lambda: under_no_grad(fs.fit_image, I1, I2, M, cam),
        "fit_image, no starts ahead (forward_starts=())": lambda: fs.fit_image(I1, I2, M, cam, forward_starts=()),
        "FreespaceRefiner() with the images": lambda: refiner(flow, M, cam, images=(I1, I2)),
        "the same, no starts ahead": lambda: ahead_off(flow, M, cam, images=(I1, I2)),
        "fit_image, max_points=10000": lambda: fs.fit_image(I1, I2, M, cam, max_points=10000),
        "FreespaceRefiner, max_points=10000": lambda: more_points(flow, M, cam, images=(I1, I2)),
        "fit_image, 20 000 points evenly spread": lambda: fs.fit_image(I1, I2, M, cam, **accurate),
        "FreespaceRefiner, 20 000 points evenly spread": lambda: accurate_refiner(flow, M, cam, images=(I1, I2)),
        "fit_image, fine_points=20000": lambda: fs.fit_image(I1, I2, M, cam, fine_points=20000),
        "FreespaceRefiner, fine_points=20000": lambda: fine_refiner(flow, M, cam, images=(I1, I2)),
        "fit_image, masked_band=True": lambda: fs.fit_image(I1, I2, M, cam, masked_band=True),
        "FreespaceRefiner, masked_band=True": lambda: masked_refiner(flow, M, cam, images=(I1, I2)),
        "FreespaceRefiner, fine_points=20000, smooth_sigma=1.0, masked_band=True":
            lambda: real_camera_refiner(flow, M, cam, images=(I1, I2)),
        "ImageGate() alone": lambda: gate(I1, I2, flow, out.flow_model, M),
        "Gaussian blur σ 4, OpenCV": lambda: gaussian_blur(grey, 4.0),
        "Gaussian blur σ 4, kornia": lambda: gaussian_blur2d(grey, (k, k), (4.0, 4.0), border_type="reflect"),
        "pyramid, 5 levels, OpenCV": lambda: image_pyramid(grey, 5, 0.0),
        "pyramid, 5 levels, torch": lambda: [x := grey] + [x := torch_decimate(x) for _ in range(4)],
        "both frames to grey, in place (to_grey)": grey_in_place,
        "both frames to grey, kornia rgb_to_grayscale": lambda: torch.cat([rgb_to_grayscale(I1), rgb_to_grayscale(I2)], 1),
        "the road's pixels, NumPy flatnonzero (mask_pixels)": lambda: mask_pixels(M),
        "the road's pixels, torch nonzero": lambda: M.reshape(-1).nonzero().squeeze(1),
        "mask pyramid, 5 levels, OpenCV": lambda: mask_pyramid(M, 5),
        "mask pyramid, 5 levels, torch": lambda: [m := M] + [m := -F.max_pool2d(-m.float(), 3, stride=2, padding=1) > 0.5
                                                             for _ in range(4)],
    }
    times = interleaved(rows, args.repeats)
    ref = np.median(times["DIS (MEDIUM), the reference"])
    print(f"{what}, {tuple(im1.shape[-2:])}, one thread, {args.repeats} interleaved repeats\n")
    print("| row | median ms | min ms | median / DIS |")
    print("|---|---|---|---|")
    for name, t in times.items():
        t = np.array(t) * 1e3
        print(f"| {name} | {np.median(t):.1f} | {t.min():.1f} | {np.median(t) / (ref * 1e3):.2f} |")
    return 0


def under_no_grad(fn, *args):
    """``fn`` (a function of the library that runs in ``torch.inference_mode``) run under
    ``torch.no_grad`` instead: the function itself, without its decorator."""
    with torch.no_grad():
        return fn.__wrapped__(*args)


def interleaved(rows: dict, repeats: int) -> dict[str, list[float]]:
    """Wall times (s) of each row's call, the rows taking turns call by call after one warm-up."""
    times = {name: [] for name in rows}
    for fn in rows.values():
        fn()
    for _ in range(repeats):
        for name, fn in rows.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    return times


def against_baseline(base, rev: str, repeats: int, I1, I2, M, cam, flow, what: str) -> None:
    """``fit_image`` and the default refiner of git revision ``rev`` (its package ``base``, from
    ``baseline.load_baseline``) against the current ones."""
    import fsof_torch as fs

    base_cam = base.Camera(cam.K, cam.height, cam.roll, cam.pitch)
    refiner, base_refiner = fs.FreespaceRefiner(), base.FreespaceRefiner()
    rows = {
        f"fit_image, {rev}": lambda: base.fit_image(I1, I2, M, base_cam),
        "fit_image, current": lambda: fs.fit_image(I1, I2, M, cam),
        f"FreespaceRefiner() with the images, {rev}": lambda: base_refiner(flow, M, base_cam, images=(I1, I2)),
        "FreespaceRefiner() with the images, current": lambda: refiner(flow, M, cam, images=(I1, I2)),
    }
    times = interleaved(rows, repeats)
    print(f"{what}, {tuple(I1.shape[-2:])}, one thread, {repeats} interleaved repeats, against {rev}\n")
    print("| row | median ms | min ms | current / baseline |")
    print("|---|---|---|---|")
    names = list(rows)
    for before, now in (names[:2], names[2:]):
        a, b = np.median(times[before]) * 1e3, np.median(times[now]) * 1e3
        print(f"| {before} | {a:.1f} | {min(times[before]) * 1e3:.1f} | |")
        print(f"| {now} | {b:.1f} | {min(times[now]) * 1e3:.1f} | {b / a:.3f} |")


if __name__ == "__main__":
    raise SystemExit(main())
