"""How ``fit_image``'s own confidence tells a right motion from a wrong one, measured.

The image fit's ``success`` tests the images under the fitted motion over the mask's pixels that
stay in view: the share of them whose plain intensities match (image 2's matched to image 1's by
their own gain and offset) within ``inlier_threshold`` grey levels, and the correlation of the
images' band of detail (``extras["correlation"]``, at least ``min_correlation`` = 0.5). This
script prints both, and how many frames succeed:

1. on the shared straight clip (every fifth pair, with road.json's polygon): the fit itself,
   the fit on degraded images (image 2 blurred by a 3 × 3 box or a 5 × 1 horizontal one, image
   2 darker by 0.7, both frames JPEG-compressed at quality 30, both with Gaussian noise σ = 4,
   both dark: × 0.2 plus noise σ = 2), the fit at 6 m a frame (every fifth frame), the fit with
   too few levels (``levels=2``: the coarsest at half size; how far it lands from the default
   fit, and whether its successes are weak, their detail correlating below 0.75), and the
   images judged at wrong motions: the fitted motion with its translation scaled by 0.5, 0 and
   −1 (every parameter held: ``fixed=`` all, ``init=`` that motion);
2. on the synthetic presets (pairs 0, 10, 20, 30 of each, the scene's road): the fit, and the
   images judged at no translation (the fit's translation × 0, every parameter held, as in 1);
   and the share of the road's band of detail near lane markings (pair 0);
3. on thin bands of the road (the KITTI 2015 pair 000000 and the clip's first pair, their
   polygons): the fit on the rows of a band only, 3, 9 and 21 rows ending 30 rows above the
   polygon's lowest row, and 9 rows from 5 below its highest; its success, correlation and z_d,
   and how far its flow lies from the fit on the whole polygon, in the band and over the polygon.

    python benchmarks/fit_confidence.py [--data DIR] [--kitti DIR]

One thread; part 1 needs the straight clip (``../shared/data/kitti_odometry_straight``, or
``--data`` naming it), part 3 the KITTI pair (``../shared/data/kitti15_000000``, or ``--kitti``).
"""

from __future__ import annotations

import argparse
import inspect
import statistics
import warnings
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_odometry_straight"
CLIP = ("calib.txt", "image_l", "road.json")
KITTI = DEFAULT.parent / "kitti15_000000"
PAIR = ("image_10.png", "image_11.png", "calib_cam_to_cam.txt", "road.json")


def box_blur(image: torch.Tensor, kx: int, ky: int) -> torch.Tensor:
    """(B, C, H, W) blurred by a kx × ky box, borders replicated."""
    padded = F.pad(image, (kx // 2, kx // 2, ky // 2, ky // 2), mode="replicate")
    return F.avg_pool2d(padded, (ky, kx), stride=1)


def jpeg(image: torch.Tensor, quality: int = 30) -> torch.Tensor:
    """(1, 3, H, W) on 0..255 through OpenCV's JPEG codec."""
    rgb = image[0].permute(1, 2, 0).clamp(0, 255).round().byte().numpy()
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    out = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return torch.from_numpy(np.ascontiguousarray(out)).permute(2, 0, 1)[None].float()


def row(name: str, fits: list) -> str:
    corr = [float(f.extras["correlation"][0]) for f in fits]
    share = [float(f.extras["inlier_fraction"][0]) for f in fits]
    ok = sum(bool(f.success[0]) for f in fits)
    return (f"| {name} | {len(fits)} | {ok} | {min(corr):.2f} / {statistics.median(corr):.2f} | "
            f"{min(share):.2f} / {statistics.median(share):.2f} |")


def marking_share(pair: dict) -> float:
    """The share of the band of detail's energy (grey image 1 minus its Gaussian blur of 4 px, as
    the fit compares it) inside a synthetic pair's road that lies within 12 px of a lane marking."""
    from fsof_torch.data.scene import LABELS
    from fsof_torch.estimation.pyramid import gaussian_blur
    from fsof_torch.evaluation.photometric import to_grey

    grey = to_grey(pair["image1"][None]).double()
    detail = (grey - gaussian_blur(grey, 4.0))[0, 0].square()
    marking = (pair["labels"] == LABELS["marking"]).float()[None, None]
    near = F.max_pool2d(marking, 25, stride=1, padding=12)[0, 0] > 0
    road = pair["road"][0]
    return float(detail[road & near].sum() / detail[road].sum())


def bands(name: str, image1: torch.Tensor, image2: torch.Tensor, road: torch.Tensor, camera) -> None:
    """Part 3: the fit on thin bands of the road's rows against the fit on the whole road."""
    from fsof_torch.estimation.image_fit import fit_image

    whole = fit_image(image1, image2, road, camera)
    rows = road[0, 0].any(1).nonzero().flatten()
    low, high = int(rows.max()), int(rows.min())
    index = torch.arange(road.shape[-2]).reshape(1, 1, -1, 1)
    print(f"\n{name}: the whole polygon (rows {high} to {low}): success {bool(whole.success[0])}, correlation "
          f"{float(whole.extras['correlation'][0]):.2f}, z_d {float(whole.params['z_d'][0]):.2f} m\n")
    print("| band of the polygon | pixels | success | correlation | z_d (m) | flow off the whole fit: in the band / "
          "over the polygon (px) |\n|---|---|---|---|---|---|")
    for n, near in ((3, True), (9, True), (21, True), (9, False)):
        # (near the car: n rows ending 30 above the polygon's lowest; far: n rows from 5 below its highest)
        first = low - 30 - n + 1 if near else high + 5
        band = road & (index >= first) & (index < first + n)
        fit = fit_image(image1, image2, band, camera)
        off = (fit.flow - whole.flow).norm(dim=1, keepdim=True)
        both = whole.valid & fit.valid
        print(f"| {n} rows, {'near the car' if near else 'far'} | {int(band.sum())} | {bool(fit.success[0])} | "
              f"{float(fit.extras['correlation'][0]):.2f} | {float(fit.params['z_d'][0]):.2f} | "
              f"{float(off[band & both].mean()):.2f} / {float(off[road & both].mean()):.1f} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    from cli import data_folder, description, present, readable_clip, readable_pair

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the straight clip's folder (default: ../shared/data/kitti_odometry_straight)")
    parser.add_argument("--kitti", type=Path, default=None, metavar="DIR",
                        help="the KITTI 2015 pair's folder (default: ../shared/data/kitti15_000000)")
    args = parser.parse_args(argv)
    data = data_folder(parser, args.data, DEFAULT, CLIP)
    kitti = data_folder(parser, args.kitti, KITTI, PAIR, option="--kitti")  # (its errors named --data)
    if args.data is not None:  # (a file it cannot read raised a traceback from part 1)
        readable_clip(parser, data)
    if args.kitti is not None:  # (a file it cannot read raised a traceback in part 3, after the clip's parts)
        readable_pair(parser, kitti, "--kitti")
    import fsof_torch as fs
    from fsof_torch.data.folders import list_images
    from fsof_torch.estimation.image_fit import fit_image

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    warnings.simplefilter("ignore")
    header = ("| condition | frames | success | correlation min / median | inlier share min / median |\n"
              "|---|---|---|---|---|")
    if present(data, CLIP, "KITTI clip (part 1)"):
        cam = fs.Camera.from_kitti(data / "calib.txt", cam=0, height=1.65)
        files = list_images(data / "image_l")  # (in frame order, as the library pairs them)
        frame = (lambda k: fs.read_image(files[k])[None])
        road = fs.read_road_mask(data / "road.json", size=tuple(frame(0).shape[-2:]))[None]
        pairs = list(range(0, 45, 5))
        g = torch.Generator().manual_seed(0)
        noisy = (lambda x, s: (x + s * torch.randn(x.shape, generator=g)).clamp(0, 255))  # noqa: E731
        variants = [
            ("the fit", lambda a, b: (a, b)),
            ("image 2 blurred, 3 × 3 box", lambda a, b: (a, box_blur(b, 3, 3))),
            ("image 2 blurred, 5 × 1 box", lambda a, b: (a, box_blur(b, 5, 1))),
            ("image 2 × 0.7", lambda a, b: (a, b * 0.7)),
            ("both JPEG, quality 30", lambda a, b: (jpeg(a), jpeg(b))),
            ("both with noise σ = 4", lambda a, b: (noisy(a, 4.0), noisy(b, 4.0))),
            ("both dark: × 0.2, noise σ = 2", lambda a, b: (noisy(a * 0.2, 2.0), noisy(b * 0.2, 2.0))),
        ]
        print(f"Shared straight clip, pairs k -> k + 1 for k in {pairs} (road.json's polygon):\n")
        print(header)
        fitted = {}
        for name, make in variants:
            fits = []
            for k in pairs:
                a, b = make(frame(k), frame(k + 1))
                fits.append(fit_image(a, b, road, cam))
                if name == "the fit":
                    fitted[k] = fits[-1]
            print(row(name, fits), flush=True)
        print(row("6 m a frame (k -> k + 5)", [fit_image(frame(k), frame(k + 5), road, cam) for k in pairs]))
        # too few levels: the coarsest (half size) is too fine for a start to reach a motion of
        # tens of pixels; how far each fit lands from the default's, as the mean flow difference
        few = [fit_image(frame(k), frame(k + 1), road, cam, levels=2) for k in pairs]
        off = [float((f.flow[0] - fitted[k].flow[0]).norm(dim=0)[road[0, 0]].mean()) for f, k in zip(few, pairs)]
        print(row("two levels only (`levels=2`)", few))
        names = tuple(fitted[pairs[0]].params)
        for scale in (0.5, 0.0, -1.0):
            fits = []
            for k in pairs:
                held = {n: v.double() for n, v in fitted[k].params.items()}
                for n in ("x_d", "y_d", "z_d"):
                    held[n] = held[n] * scale
                fits.append(fit_image(frame(k), frame(k + 1), road, cam, fixed=names, init=held))
            print(row(f"held at the fit's translation × {scale:g}", fits), flush=True)
        weak = [float(f.extras["correlation"][0]) for f in few if bool(f.success[0])]
        # (a success is clear from halfway between the bar and 1: fit_image's own rule)
        clear = 0.5 * (1 + inspect.signature(fit_image).parameters["min_correlation"].default)
        print(f"\nTwo levels only: off the default fit by {min(off):.0f} to {max(off):.0f} px (road mean); "
              f"{len(weak)} successes, correlating {max(weak, default=float('nan')):.2f} at most "
              f"(weak below {clear:g})\n")
    print("Synthetic presets, pairs 0, 10, 20, 30 (the scene's road): the fit, and the images judged at no "
          "translation (the fit's × 0, every parameter held)\n")
    print(header)
    shares = []
    for preset in fs.PRESETS:
        fits, still = [], []
        for i in (0, 10, 20, 30):
            p = fs.render_pair(preset, i)
            images = (p["image1"][None], p["image2"][None], p["road"][None], p["camera"])
            fits.append(fit_image(*images))
            held = {n: v.double() * (0.0 if n in ("x_d", "y_d", "z_d") else 1.0) for n, v in fits[-1].params.items()}
            still.append(fit_image(*images, fixed=tuple(held), init=held))
        print(row(f"synthetic `{preset}`", fits), flush=True)
        print(row(f"synthetic `{preset}`, held at no translation", still), flush=True)
        shares.append(f"{preset} {marking_share(fs.render_pair(preset, 0)):.2f}")
    print("\nShare of the road's band of detail (energy) within 12 px of a lane marking, pair 0: " + ", ".join(shares))
    if present(kitti, PAIR, "KITTI 2015 pair (part 3)"):
        read = (lambda name: fs.read_image(kitti / name)[None])  # noqa: E731
        road = fs.read_road_mask(kitti / "road.json", size=tuple(read(PAIR[0]).shape[-2:]))[None]
        bands("KITTI 2015 pair 000000", read(PAIR[0]), read(PAIR[1]), road,
              fs.Camera.from_kitti(kitti / PAIR[2], cam=2, height=1.65))
    if present(data, CLIP, "KITTI clip (part 3)"):
        files = list_images(data / "image_l")
        first = fs.read_image(files[0])[None]
        bands("KITTI clip, pair 0", first, fs.read_image(files[1])[None],
              fs.read_road_mask(data / "road.json", size=tuple(first.shape[-2:]))[None],
              fs.Camera.from_kitti(data / "calib.txt", cam=0, height=1.65))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
