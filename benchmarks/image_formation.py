"""Where the image fit's error on rendered frames comes from: the road's geometry between the
frames, or how the renderer forms each frame's fine detail.

For pairs of the synthetic ``body-motion`` preset and of the ``default`` scene in a sharp turn
(``steering=0.1``), the road end-point error (px, valid road pixels) of ``fit_image`` with its
defaults (the band of detail, 3000 points) and with plain intensities and 20 000 points, on:

- ``rendered``: the pair as rendered;
- ``warped``: image 2 replaced by image 1 warped by the true road homography (the exported
  ``plane`` motion, OpenCV ``warpPerspective``, bicubic). The motion and the magnification between
  the frames are the same, but the road's detail is image 1's, moved: nothing of it changes;
- ``coarse asphalt``: the pair rendered with the asphalt's two finest noise octaves (cells 2 and
  5 cm) switched off. The renderer band-limits the texture per pixel footprint, so as the road
  comes nearer those octaves fade in: image 2 near the car shows detail image 1 did not;
- ``no cars``: the pair rendered without parked or moving cars (nothing occludes the road or
  moves over it);
- ``matched``: image 2 as rendered, blurred where the true road motion magnifies the road
  (:func:`matched`): at each of its pixels by the Gaussian that takes its pixel footprint to
  image 1's footprint mapped there, σ² = s² (J Jᵀ − I) along each axis (J the true homography's
  Jacobian from image 1 to image 2, s = ``--matched-sigma``, 1 px by default). A bound on what
  comparing the frames at matched scale could bring: it knows the true motion.

    python benchmarks/image_formation.py [--pairs 4] [--matched-sigma 1.0] [--from-truth [--warped]]

With ``--from-truth``, instead: where the cost's minimum lies. On the same ``body-motion`` pairs
each fit starts at the true motion and is solved at full resolution only (``levels=1``; no prior,
no bounds, no other starts), on the rendered frames, with the points chosen as by default (the
3000 of strongest gradient among 6000 evenly spread), 3000, 20 000 or every road pixel evenly
spread (``gradient_fraction=1``), and every road pixel but those within 8 px of the kerb and the
pavement (which stand 12 cm above the road); then three of these with each band's blur taken
inside the road mask (``masked_band=True``): per row the mean road EPE (px), the mean |error| of
the camera's pitch and roll over the road (°), and the mean error of z_d (camera heights). With
``--warped`` as well, on the pairs with image 2 replaced by image 1 warped by the true motion
(``warped`` above): where nothing but the motion changes between the frames.

One thread.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

FITS = {"defaults": {}, "plain intensities, 20 000 points": {"highpass": None, "max_points": 20000}}


def true_homography(pair: dict) -> np.ndarray:
    """The road homography (pixels of image 1 -> image 2) of the pair's exported plane motion."""
    from fsof_torch.geometry.road_models import get_road_model

    model = get_road_model("plane")
    # (the plane's translation is in units of its own height over the road at t, which the body's
    # heave moves away from the nominal camera's)
    camera = pair["camera"].to(torch.float64).replace(height=pair["plane"]["height"])
    values = torch.tensor([[pair["plane"][n] for n in model.params]], dtype=torch.float64)
    return model.matrix(camera, values)[0].numpy()


def warped(pair: dict) -> torch.Tensor:
    """Image 1 warped by the true road homography into image 2's frame (3, H, W)."""
    import cv2

    H, W = pair["image1"].shape[-2:]
    src = pair["image1"].permute(1, 2, 0).numpy().astype(np.float32)
    dst = cv2.warpPerspective(src, true_homography(pair), (W, H), flags=cv2.INTER_CUBIC,
                              borderMode=cv2.BORDER_REPLICATE)
    return torch.from_numpy(dst).permute(2, 0, 1).clamp(0, 255)


def magnification_blur(M: np.ndarray, size: tuple[int, int], s: float) -> np.ndarray:
    """Per pixel of image 2 (``size`` (H, W)), the standard deviations (2, H, W) (px, along x and
    y) of the blur that widens its pixel footprint, a Gaussian of ``s`` px, to image 1's mapped
    there by the road homography ``M`` (image 1 -> image 2): the diagonal of s² (J Jᵀ − I), J the
    map's Jacobian at the pixel's preimage, clipped at 0 (where image 2 shrinks the road, and
    behind the camera's horizon)."""
    H, W = size
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x1 = np.linalg.inv(M) @ np.stack([u.ravel(), v.ravel(), np.ones(H * W)])
    ahead = x1[2] > 0
    x1 = x1 / np.where(ahead, x1[2], 1.0)
    w = M[2] @ x1
    x2 = (M[:2] @ x1) / w
    J = (M[:2, :2, None] - x2[:, None, :] * M[2, :2][None, :, None]) / w  # (2, 2, N): ∂x2_i / ∂x1_j
    widen = np.where(ahead, np.clip((J ** 2).sum(1) - 1.0, 0.0, None), 0.0)
    return (s * np.sqrt(widen)).reshape(2, H, W)


#: the blurs (px) computed once per axis for :func:`matched`, between which each pixel interpolates
BLUR_STEPS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)


def blur_along(image: np.ndarray, sigma: np.ndarray, axis: int) -> np.ndarray:
    """``image`` (H, W, C) float32 blurred along ``axis`` (0: x, 1: y) by a Gaussian of a
    standard deviation per pixel (``sigma`` (H, W), px, at most 6): linearly between OpenCV's
    blurs at :data:`BLUR_STEPS`."""
    import cv2

    steps = np.array(BLUR_STEPS)
    stack = [image]
    for s in steps[1:]:
        k = 2 * math.ceil(3 * s) + 1
        stack.append(cv2.GaussianBlur(image, (k, 1) if axis == 0 else (1, k), s if axis == 0 else 0,
                                      sigmaY=s if axis == 1 else 1e-9))
    sigma = np.clip(sigma, 0.0, steps[-1])
    i = np.clip(np.searchsorted(steps, sigma, side="right") - 1, 0, len(steps) - 2)
    t = ((sigma - steps[i]) / (steps[i + 1] - steps[i]))[..., None]
    rows, cols = np.indices(sigma.shape)
    stack = np.stack(stack)
    return (stack[i, rows, cols] * (1 - t) + stack[i + 1, rows, cols] * t).astype(np.float32)


def matched(pair: dict, s: float) -> torch.Tensor:
    """Image 2 (3, H, W) blurred by its magnification under the true road motion
    (:func:`magnification_blur`), along x, then along y."""
    image = pair["image2"].permute(1, 2, 0).numpy().astype(np.float32)
    sx, sy = magnification_blur(true_homography(pair), image.shape[:2], s)
    return torch.from_numpy(blur_along(blur_along(image, sx, 0), sy, 1)).permute(2, 0, 1)


def epe(fit, pair: dict) -> float:
    road = (pair["road"] & pair["valid"])[0]
    return float((fit.flow[0] - pair["flow"]).norm(dim=0)[road].mean())


#: ``--from-truth``: the points of each row (``fit_image`` options) and the pixels left out of the
#: road mask (within this many px of the kerb and pavement; 0: none)
FROM_TRUTH = {"3000 points, strongest gradient of 6000 (default)": ({}, 0),
              "3000 points evenly spread": ({"gradient_fraction": 1.0}, 0),
              "20 000 points evenly spread": ({"max_points": 20000, "gradient_fraction": 1.0}, 0),
              "every road pixel": ({"max_points": None, "gradient_fraction": 1.0}, 0),
              "every road pixel but those within 8 px of kerb and pavement": ({"max_points": None,
                                                                              "gradient_fraction": 1.0}, 8),
              "3000, strongest gradient of 6000, band inside the mask": ({"masked_band": True}, 0),
              "20 000 evenly spread, band inside the mask": ({"max_points": 20000, "gradient_fraction": 1.0,
                                                              "masked_band": True}, 0),
              "every road pixel, band inside the mask": ({"max_points": None, "gradient_fraction": 1.0,
                                                          "masked_band": True}, 0)}


def off_kerb(pair: dict, pixels: int) -> torch.Tensor:
    """The pair's road mask (1, H, W) without the pixels within ``pixels`` px of the kerb and the
    pavement (its ``labels``)."""
    import torch.nn.functional as F

    from fsof_torch.data.scene.config import KERB, PAVEMENT

    labels = pair["labels"].reshape(1, *pair["labels"].shape[-2:])
    raised = ((labels == KERB) | (labels == PAVEMENT)).to(torch.float32)
    return pair["road"] & ~(F.max_pool2d(raised, 2 * pixels + 1, 1, pixels) > 0)


def from_truth(pairs: list[dict]) -> None:
    """The ``--from-truth`` table (see the module)."""
    from fsof_torch import fit_image
    from fsof_torch.geometry.road_models import get_road_model

    model = get_road_model("plane")
    print("| points | road EPE (px) | pitch error (°) | roll error (°) | z_d error (camera heights) |")
    print("|---|---|---|---|---|")
    for name, (options, near_kerb) in FROM_TRUTH.items():
        rows = []
        for p in pairs:
            camera = p["camera"].to(torch.float64).replace(height=p["plane"]["height"])
            truth = {n: p["plane"][n] for n in model.params}
            mask = off_kerb(p, near_kerb) if near_kerb else p["road"]
            fit = fit_image(p["image1"][None].double(), p["image2"][None].double(), mask[None], camera, init=truth,
                            levels=1, prior=None, bounds=None, forward_starts=(), turn_starts=(), reverse_starts=(),
                            retry_starts=0, retry_without_prior=False, **options)
            error = {n: float(fit.params[n][0]) - truth[n] for n in ("pitch", "roll", "z_d")}
            rows.append((epe(fit, p), abs(math.degrees(error["pitch"])), abs(math.degrees(error["roll"])), error["z_d"]))
        e, pitch, roll, z = np.mean(rows, axis=0)
        print(f"| {name} | {e:.3f} | {pitch:.3f} | {roll:.3f} | {z:+.4f} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    from cli import description, pair_count

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--pairs", type=pair_count(spacing=2), default=4,
                        help="pairs of each scene (default 4; the turning scene's are 2 frames apart)")
    parser.add_argument("--from-truth", action="store_true",
                        help="instead, fits of the body-motion pairs started at the true motion, at full resolution, "
                             "by the points they use")
    parser.add_argument("--warped", action="store_true",
                        help="with --from-truth: image 2 replaced by image 1 warped by the true road motion")
    parser.add_argument("--matched-sigma", type=float, default=1.0, metavar="S",
                        help="the pixel footprint (px, a Gaussian's σ) of the matched rows' blur, in (0, 4] "
                             "(default 1)")
    args = parser.parse_args(argv)
    if not 0 < args.matched_sigma <= 4:
        parser.error(f"--matched-sigma: expected a footprint in (0, 4] px, got {args.matched_sigma}")
    if args.warped and not args.from_truth:
        parser.error("--warped: only with --from-truth")
    torch.set_num_threads(1)
    import cv2

    cv2.setNumThreads(1)
    from fsof_torch import fit_image
    from fsof_torch.data.scene import render_pair, render_sequence, scene_config

    if args.from_truth:
        pairs = render_sequence("body-motion", args.pairs, seed=0)
        from_truth([{**p, "image2": warped(p)} for p in pairs] if args.warped else pairs)
        return 0
    scenes = {"body-motion": ("body-motion", {}), "turning": ("default", {"steering": 0.1})}
    print("| scene | frames | " + " | ".join(f"{name}: EPE per pair (px) | mean" for name in FITS) + " |")
    print("|---|---|" + "---|---|" * len(FITS))
    for scene, (preset, overrides) in scenes.items():
        asphalt = scene_config(preset, **overrides).asphalt
        coarse = (0.0, 0.0) + tuple(asphalt[2:])
        indices = range(args.pairs) if scene == "body-motion" else range(0, 2 * args.pairs, 2)
        def render(**changes):
            if scene == "body-motion":  # consecutive pairs (they share frames: each rendered once)
                return render_sequence(preset, args.pairs, seed=0, **overrides, **changes)
            return [render_pair(preset, i, seed=0, **overrides, **changes) for i in indices]

        rendered = render()
        variants = {"rendered": [(p, p["image2"]) for p in rendered],
                    "warped": [(p, warped(p)) for p in rendered],
                    "coarse asphalt": [(p, p["image2"]) for p in render(asphalt=coarse)],
                    "no cars": [(p, p["image2"]) for p in render(parked_cars=0.0, moving_cars=0.0)],
                    "matched": [(p, matched(p, args.matched_sigma)) for p in rendered]}
        for variant, items in variants.items():
            cells = []
            for options in FITS.values():
                errors = [epe(fit_image(p["image1"][None], image2[None], p["road"][None], p["camera"], **options), p)
                          for p, image2 in items]
                cells.append(f"{' / '.join(f'{e:.3f}' for e in errors)} | {np.mean(errors):.3f}")
            print(f"| {scene} | {variant} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
