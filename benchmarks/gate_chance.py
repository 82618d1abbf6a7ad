"""How often the gate's tests decide by chance where the images carry no evidence.

Image 1 is a smooth random texture (96 × 192, grey levels 0..255); image 2 an unrelated texture
of the same kind, so no flow explains the pair. The prediction is a constant 3 px to the right,
the model the same plus a flow error that varies smoothly over the image (up to ``--error`` px,
as a network's does). Over ``--draws`` draws (each of both textures and of the error), per
``z``: the number of draws whose images *confirm* the model (``out.confirmed``: the model better
than the prediction over the mask by ``z`` standard errors) and whose model is used anywhere.
Under independent points a one-sided test at z = 2 errs in about 2 % of draws; the judged
points' census rings overlap and the textures are correlated over several pixels, so the gate
takes a sample's standard error from blocks of points. The last two columns give the same
counts with the points' own standard error alone (as if they were independent: the gate's
blocks switched off for the comparison)
([refinement.md](../docs/refinement.md#the-gate-never-worse-than-the-prediction-where-the-images-can-tell)).

    python benchmarks/gate_chance.py [--draws 100] [--error 2.0]

One thread, about ten seconds.
"""

from __future__ import annotations

import argparse
import contextlib
from typing import Iterator

import torch
import torch.nn.functional as F

H, W = 96, 192


def texture(seed: int) -> torch.Tensor:
    """(1, 1, H, W) smooth random grey levels: noise on a quarter grid, bicubic up."""
    g = torch.Generator().manual_seed(seed)
    noise = torch.rand(1, 1, H // 4, W // 4, generator=g) * 255
    return F.interpolate(noise, size=(H, W), mode="bicubic", align_corners=False).clamp(0, 255)


def smooth_error(amplitude: float, seed: int) -> torch.Tensor:
    """(1, 2, H, W) a flow error varying smoothly over the image, in [-amplitude, amplitude] px."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 2, H // 16, W // 16, generator=g) * 2 - 1
    return amplitude * F.interpolate(coarse, size=(H, W), mode="bilinear", align_corners=False)


@contextlib.contextmanager
def independent_points() -> Iterator[None]:
    """The gate with its points' standard error alone (its blocks' error not taken)."""
    from fsof_torch.refinement import gate

    blocked = gate._mean_and_error
    gate._mean_and_error = lambda v, w, *blocks: blocked(v, w)
    try:
        yield
    finally:
        gate._mean_and_error = blocked


def main(argv: list[str] | None = None) -> int:
    from cli import description, finite_float, positive_int

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--draws", type=positive_int, default=100,
                        help="draws of the textures and the model's error (default 100)")
    parser.add_argument("--error", type=finite_float, default=2.0, help="the model's largest error, px (default 2)")
    args = parser.parse_args(argv)
    if args.error <= 0:
        parser.error(f"--error: expected a positive number of pixels, got {args.error:g}")
    from fsof_torch.refinement.gate import ImageGate

    torch.set_num_threads(1)
    prediction = torch.zeros(1, 2, H, W)
    prediction[:, 0] = 3.0
    mask = torch.ones(1, 1, H, W, dtype=torch.bool)
    print(f"image 1 and an unrelated image 2 ({H} x {W}), model = prediction + a smooth error up to "
          f"{args.error:g} px, {args.draws} draws of both")
    print("| z | draws confirming the model | draws using the model anywhere "
          "| as independent points: confirming | using |")
    print("|---|---|---|---|---|")
    for z in (2.0, 3.0, 4.0):
        gate = ImageGate(z=z)
        counts = []
        for points_only in (False, True):
            confirmed = used = 0
            with independent_points() if points_only else contextlib.nullcontext():
                for draw in range(args.draws):
                    image1, image2 = texture(2 * draw), texture(2 * draw + 1)
                    model = prediction + smooth_error(args.error, 10_000 + draw)
                    out = gate(image1, image2, prediction, model, mask)
                    confirmed += int(out.confirmed[0])
                    used += int(out.model_used[0])
            counts += [confirmed, used]
        print(f"| {z:g} | " + " | ".join(f"{c} of {args.draws}" for c in counts) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
