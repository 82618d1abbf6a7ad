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
2. on the synthetic presets (pairs 0, 10, 20, 30 of each, the scene's road): the fit.

    python benchmarks/fit_confidence.py [--data DIR]

One thread; part 1 needs the straight clip (``../shared/data/kitti_odometry_straight``, or
``--data`` naming it).
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


def main(argv: list[str] | None = None) -> int:
    from cli import data_folder, description, present

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="the straight clip's folder (default: ../shared/data/kitti_odometry_straight)")
    args = parser.parse_args(argv)
    data = data_folder(parser, args.data, DEFAULT, CLIP)
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
    print("Synthetic presets, pairs 0, 10, 20, 30 (the scene's road):\n")
    print(header)
    for preset in fs.PRESETS:
        fits = []
        for i in (0, 10, 20, 30):
            p = fs.render_pair(preset, i)
            fits.append(fit_image(p["image1"][None], p["image2"][None], p["road"][None], p["camera"]))
        print(row(preset, fits), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
