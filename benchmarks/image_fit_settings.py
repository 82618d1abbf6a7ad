"""The image fit's photometric settings on real and synthetic frames: the band-pass width, the
pre-smoothing and the number of points, compared by road end-point error where the truth is known.

For each setting (``fit_image`` keyword arguments, JSON), the ``"plane"`` fit of:

- the shared KITTI 2015 pair 000000 (road.json; EPE over the road pixels with ground truth), as
  given and through the 16 windows 4 pixels smaller than the frame at offsets 0–3 from its top
  and left (:func:`crops`): the same scene and motion, but the fit's points fall elsewhere. A
  single frame's figure moves by a tenth of a pixel with that draw; the crops' mean does not;
- three pairs of the shared straight KITTI odometry clip (0, 4, 8; road census distance of the
  fitted road flow, image 1 against image 2 warped, 7×7 census / 48);
- the synthetic ``default`` scene (pairs 0, 2, 10, 20), ``body-motion`` preset (pairs 0–3), and
  the ``default`` scene in a sharp turn (``steering=0.1``: 2.6° of yaw per frame, 26°/s at 10 Hz;
  pairs 0, 2, 10), road EPE over the valid road pixels.

With ``--mirror`` the real frames are mirrored left to right first (``real_road.mirrored``: the
same street seen from its other side, the camera mirrored with it). With ``--noise GREY`` the
synthetic frames carry that much sensor noise (the scenes' ``noise``, grey levels at 375×1242;
``SENSOR_NOISE`` = 3.8 matches the fine-scale contrast measured on the real KITTI road); by
default they carry none, as the presets render.

The time these settings cost: ``bench_image_fit.py`` (the default, ``max_points=10000`` and
20 000 evenly spread points).

    python benchmarks/image_fit_settings.py                       # the settings below
    python benchmarks/image_fit_settings.py '{"highpass": 3.0}' '{"highpass": null}'
    python benchmarks/image_fit_settings.py --mirror '{}'
    python benchmarks/image_fit_settings.py --noise 3.8 '{}' '{"smooth_sigma": 0.7}'

Without ``../shared`` the real columns are skipped. One thread.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SETTINGS = ['{}', '{"max_points": 10000}', '{"highpass": null}', '{"highpass": null, "smooth_sigma": 1.0}',
            '{"highpass": 5.0, "smooth_sigma": 1.0}', '{"highpass": 3.0}', '{"highpass": 3.0, "smooth_sigma": 1.0}',
            '{"highpass": 10.0}', '{"gradient_fraction": 1.0}', '{"max_points": 20000, "gradient_fraction": 1.0}',
            '{"max_points": null, "gradient_fraction": 1.0}', '{"fine_points": 20000}', '{"smooth_sigma": 0.5}',
            '{"smooth_sigma": 0.7}', '{"smooth_sigma": 1.0}', '{"fine_points": 20000, "smooth_sigma": 0.7}',
            '{"fine_points": 20000, "smooth_sigma": 1.0}']
SHIFT = 4
KITTI15 = ("image_10.png", "image_11.png", "flow_noc_10.png", "road.json", "calib_cam_to_cam.txt")
CLIP = ("image_l", "calib.txt", "road.json")


def crops(sample: dict, shift: int = SHIFT) -> list[dict]:
    """``sample`` (a ``camera`` and tensors whose last two dimensions are the frame's (H, W)) seen
    through the ``shift`` × ``shift`` windows of (H − shift, W − shift) pixels at offsets
    0..shift − 1 from the top and the left: the tensors sliced, the camera's principal point moved
    (:meth:`~fsof_torch.Camera.cropped`)."""
    H, W = sample["image1"].shape[-2:]
    h, w = H - shift, W - shift
    out = []
    for top in range(shift):
        for left in range(shift):
            window = {k: (v[..., top:top + h, left:left + w] if torch.is_tensor(v) and v.shape[-2:] == (H, W) else v)
                      for k, v in sample.items() if k != "camera"}
            window["camera"] = sample["camera"].cropped(left, top, W - left - w, H - top - h)
            out.append(window)
    return out


def road_epe(flow: torch.Tensor, sample: dict) -> float:
    """Mean end-point error (px) of a flow (2, H, W) over the sample's road pixels with ground truth."""
    road = (sample["road"] & sample["valid"]).reshape(flow.shape[-2:])
    return float((flow - sample["flow"]).norm(dim=0)[road].mean())


def mirrored_samples(real: dict) -> dict:
    """The real samples (``"kitti"``: a sample dict; ``"clip"``: (camera, image1, image2, road)
    tuples) mirrored left to right (``real_road.mirrored``)."""
    from real_road import mirrored

    out = dict(real)
    if "kitti" in real:
        out["kitti"] = mirrored(real["kitti"])
    if "clip" in real:
        keys = ("camera", "image1", "image2", "road")
        out["clip"] = [tuple(mirrored(dict(zip(keys, sample)))[k] for k in keys) for sample in real["clip"]]
    return out


def main(argv: list[str] | None = None) -> int:
    from cli import check_options, description, finite_float, json_object, present

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("settings", type=json_object, nargs="*", metavar="SETTING",
                        help="fit_image keyword arguments as a JSON object (not the images, mask or camera), one row "
                             "each (default: the settings of the documented table)")
    parser.add_argument("--mirror", action="store_true", help="mirror the real frames left to right first")
    parser.add_argument("--noise", type=finite_float, default=0.0, metavar="GREY",
                        help="sensor noise of the synthetic frames, grey levels at 375x1242 (default 0: none, as the "
                             "presets render; 3.8 matches the real KITTI road's fine-scale contrast)")
    args = parser.parse_args(argv)
    if not 0.0 <= args.noise <= 255.0:
        parser.error(f"--noise: expected grey levels within [0, 255], got {args.noise!r}")
    from fsof_torch import Camera, fit_image, photometric_error, read_image, read_kitti_flow, read_road_mask
    from fsof_torch.data.folders import list_images
    from fsof_torch.data.scene import render_pair, render_sequence

    for kw in args.settings:
        check_options(parser, kw, "SETTING", fit_image, reserved=("image1", "image2", "mask", "camera"))

    torch.set_num_threads(1)
    try:
        import cv2
        cv2.setNumThreads(1)
    except ImportError:  # (only the real columns read images with OpenCV)
        pass
    settings = args.settings or [json.loads(a) for a in SETTINGS]
    noise = args.noise
    synthetic = {"default": [render_pair("default", i, seed=0, noise=noise) for i in (0, 2, 10, 20)],
                 "body-motion": render_sequence("body-motion", 4, seed=0, noise=noise),
                 "turning": [render_pair("default", i, seed=0, steering=0.1, noise=noise) for i in (0, 2, 10)]}
    real = {}
    k15 = SHARED / "kitti15_000000"
    if present(k15, KITTI15, "KITTI pair kitti15_000000 (the KITTI columns)"):
        im1, im2 = read_image(k15 / "image_10.png"), read_image(k15 / "image_11.png")
        gt, valid = read_kitti_flow(k15 / "flow_noc_10.png")
        road = read_road_mask(k15 / "road.json", size=tuple(im1.shape[-2:]))
        real["kitti"] = {"camera": Camera.from_kitti(k15 / "calib_cam_to_cam.txt", cam=2, height=1.65),
                         "image1": im1, "image2": im2, "road": road, "flow": gt, "valid": valid}
    clip = SHARED / "kitti_odometry_straight"
    if present(clip, CLIP, "KITTI clip kitti_odometry_straight (the clip column)"):
        files = list_images(clip / "image_l")  # (in frame order, as the library pairs them)
        cam = Camera.from_kitti(clip / "calib.txt", cam=0, height=1.65)
        road = read_road_mask(clip / "road.json", size=tuple(read_image(files[0]).shape[-2:]))
        real["clip"] = [(cam, read_image(files[i]), read_image(files[i + 1]), road) for i in (0, 4, 8)]
    if args.mirror:
        real = mirrored_samples(real)

    def fit(sample: dict, kw: dict) -> torch.Tensor:
        return fit_image(sample["image1"][None], sample["image2"][None], sample["road"][None], sample["camera"],
                         **kw).flow[0]

    print(f"| setting | KITTI pair EPE (px), as given | KITTI pair EPE (px), {SHIFT * SHIFT} crops: mean (min–max) "
          "| clip census | default EPE (px) | body-motion EPE (px) | turning EPE (px) |")
    print("|---|---|---|---|---|---|---|")
    for kw in settings:
        cols = []
        if "kitti" in real:
            cols.append(f"{road_epe(fit(real['kitti'], kw), real['kitti']):.3f}")
            errors = []
            for window in crops(real["kitti"]):
                errors.append(road_epe(fit(window, kw), window))
            cols.append(f"{np.mean(errors):.3f} ({min(errors):.3f}–{max(errors):.3f})")
        else:
            cols += ["–", "–"]
        if "clip" in real:
            c = []
            for cam, im1, im2, road in real["clip"]:
                flow = fit_image(im1[None], im2[None], road[None], cam, **kw).flow
                c.append(float(photometric_error(im1[None], im2[None], flow.float(), road[None], kind="census")[0]))
            cols.append(f"{np.mean(c):.4f}")
        else:
            cols.append("–")
        for pairs in synthetic.values():
            cols.append(f"{np.mean([road_epe(fit(p, kw), p) for p in pairs]):.3f}")
        print(f"| `{json.dumps(kw)}` | " + " | ".join(cols) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
