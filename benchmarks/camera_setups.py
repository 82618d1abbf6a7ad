"""The image fit and the default refiner across camera set-ups: intrinsics, image sizes, mounting
heights and angles, frame rates and speeds beyond KITTI's.

Each set-up renders the ``body-motion`` preset (the default scene with the body oscillating over a
level road: ±1° pitch and roll, ±2 cm height) through another camera: its K at the rendered size
(focal length, principal point, non-square pixels), mounting height, pitch and roll, frame
interval and speed. On each pair OpenCV DIS (MEDIUM) predicts the flow, ``fit_image`` fits the
road's motion to the two images (road mask, calibrated camera, defaults), and the default
``FreespaceRefiner()`` refines DIS's flow with the images and no odometry. Prints per set-up the
road end-point error (px, pooled over the pairs' valid road pixels) of DIS, of the image fit's
model flow and of the refined flow, how many fits succeeded and how many pairs were refined.

    python benchmarks/camera_setups.py [--pairs 0 1] [--setups kitti robot-0.5m ...] [--noise GREY]
"""

from __future__ import annotations

import argparse
import math
import warnings

import torch

_DEG = math.pi / 180.0


def _K(f: float, W: int, H: int, cx: float | None = None, cy: float | None = None, fy: float | None = None) -> tuple:
    """Intrinsics at (H, W): the principal point at the image's centre unless given."""
    return ((f, 0.0, (W - 1) / 2 if cx is None else cx), (0.0, f if fy is None else fy, (H - 1) / 2 if cy is None else cy),
            (0.0, 0.0, 1.0))


#: name -> SceneConfig overrides of the body-motion preset (the K given at the rendered size)
SETUPS: dict[str, dict] = {
    "kitti": {},
    "robot-0.25m-15Hz": dict(size=(480, 640), K=_K(400, 640, 480), height=0.25, pitch=0.0, roll=0.0, dt=1 / 15,
                             speed=1.0, kerb_height=0.08),
    "robot-0.5m-30Hz": dict(size=(480, 640), K=_K(500, 640, 480), height=0.5, pitch=-5 * _DEG, roll=0.0, dt=1 / 30,
                            speed=1.5, kerb_height=0.1),
    # the horizon above the image's top edge: every row below it is ground
    "robot-floor-pitch-35": dict(size=(480, 640), K=_K(500, 640, 480), height=0.5, pitch=-35 * _DEG, roll=0.0,
                                 dt=0.1, speed=1.0, kerb_height=0.1, buildings=False),
    "qvga-320x240": dict(size=(240, 320), K=_K(260, 320, 240), height=1.3, pitch=-2 * _DEG, speed=10.0),
    "wide-640x480-f300": dict(size=(480, 640), K=_K(300, 640, 480), height=1.4, pitch=-3 * _DEG, speed=10.0),
    "car-1.2m-720p": dict(size=(720, 1280), K=_K(1000, 1280, 720), height=1.2, pitch=-3 * _DEG, roll=0.5 * _DEG),
    # a 540-row band cut from a 1080p frame: the principal point well above the band's centre
    "car-1080p-crop-540x1920": dict(size=(540, 1920), K=_K(1400, 1920, 540, cy=200.0), height=1.2, pitch=0.0, roll=0.0),
    "car-1080p-30Hz": dict(size=(1080, 1920), K=_K(1400, 1920, 1080), height=1.4, pitch=-2 * _DEG, dt=1 / 30,
                           speed=15.0),
    "portrait-1024x512": dict(size=(1024, 512), K=_K(700, 512, 1024), height=1.4, pitch=-8 * _DEG, roll=0.0,
                              speed=10.0),
    "non-square-off-centre": dict(K=_K(700, 1242, 375, cx=500.0, cy=220.0, fy=760.0)),
    "pitch+5-roll-3": dict(pitch=5 * _DEG, roll=-3 * _DEG),
    "truck-3m-pitch-10": dict(size=(480, 640), K=_K(600, 640, 480), height=3.0, pitch=-10 * _DEG, roll=0.0,
                              speed=15.0),
    "truck-3m-5Hz": dict(size=(480, 640), K=_K(600, 640, 480), height=3.0, pitch=-6 * _DEG, roll=1 * _DEG, dt=0.2,
                         speed=20.0),
    "kitti-2Hz-2m/s": dict(dt=0.5, speed=2.0),
    "kitti-30Hz": dict(dt=1 / 30),
    "car-1.2m-5Hz-12m/s": dict(height=1.2, dt=0.2, speed=12.0),
    "car-1.2m-5Hz-25m/s": dict(height=1.2, dt=0.2, speed=25.0),
}


def setup_config(name: str, noise: float):
    """The checked SceneConfig of set-up ``name`` with ``noise`` grey levels of sensor noise at its own size."""
    from fsof_torch.data.scene import scene_config

    overrides = dict(SETUPS[name])
    if "size" in overrides:
        overrides["base_size"] = overrides["size"]  # (K is given at the rendered size)
    return scene_config("body-motion", noise=noise, **overrides)


def main(argv: list[str] | None = None) -> int:
    from cli import description, finite_float, pair_index, scene_seed

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--pairs", type=pair_index, nargs="+", default=[0, 1],
                        help="pair indices of each set-up's sequence (default 0 1)")
    parser.add_argument("--setups", nargs="+", default=list(SETUPS), choices=list(SETUPS), metavar="NAME",
                        help=f"the camera set-ups (default: all of {', '.join(SETUPS)})")
    parser.add_argument("--seed", type=scene_seed, default=0, help="the scenes' seed, in [0, 2**62) (default 0)")
    parser.add_argument("--noise", type=finite_float, default=0.0, metavar="GREY",
                        help="sensor noise of the frames, grey levels at each set-up's own size (default 0: none)")
    args = parser.parse_args(argv)
    if not 0.0 <= args.noise <= 255.0:
        parser.error(f"--noise: expected grey levels within [0, 255], got {args.noise!r}")
    torch.set_num_threads(1)
    import cv2

    import fsof_torch as fs
    from refine.sources import dis_flow

    cv2.setNumThreads(1)
    warnings.simplefilter("ignore")
    refiner = fs.FreespaceRefiner(warn=False)
    print(f"body-motion scene through each camera, pairs {args.pairs} (seed {args.seed}, noise {args.noise:g}); "
          "road EPE in px pooled over the pairs' valid road pixels")
    print(f"{'set-up':<24} {'H x W':>10} {'f (px)':>7} {'h (m)':>5} {'pitch':>6} {'roll':>5} {'Hz':>4} {'m/frame':>7}"
          f"  {'DIS':>7} {'fit':>7} {'fit ok':>6} {'refined':>8} {'refined pairs':>13}")
    for name in args.setups:
        cfg = setup_config(name, args.noise)
        sums = torch.zeros(3, dtype=torch.float64)
        count, ok, refined = 0, 0, 0
        for k in args.pairs:
            p = fs.render_pair(cfg, k, seed=args.seed)
            im1, im2, road, camera = p["image1"][None], p["image2"][None], p["road"][None], p["camera"]
            flow = dis_flow(p["image1"], p["image2"])[None]
            fit = fs.fit_image(im1, im2, road, camera)
            out = refiner(flow, road, camera, images=(im1, im2))
            use = (p["road"] & p["valid"])[0]
            for i, f in enumerate((flow, fit.flow, out.flow)):
                sums[i] += (f[0] - p["flow"]).norm(dim=0)[use].double().sum()
            count += int(use.sum())
            ok += int(fit.success.sum())
            refined += int(out.refined.sum())
        dis, model, ref = (sums / max(count, 1)).tolist()
        H, W = cfg.size or cfg.base_size
        n = len(args.pairs)
        print(f"{name:<24} {f'{H}x{W}':>10} {cfg.K[0][0]:7.0f} {cfg.height:5.2f} {math.degrees(cfg.pitch):+6.1f} "
              f"{math.degrees(cfg.roll):+5.1f} {1 / cfg.dt:4.0f} {abs(cfg.speed * cfg.speed_factor * cfg.dt):7.2f}"
              f"  {dis:7.3f} {model:7.3f} {f'{ok}/{n}':>6} {ref:8.3f} {f'{refined}/{n}':>13}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
