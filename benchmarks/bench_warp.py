"""Speed of fsof_torch.evaluation.warp.warp_backward against a single kornia bilinear remap (reference),
and of the photometric error kinds built on it against the warp alone (reference).

warp_backward samples bilinearly as four nearest-neighbour taps so that whole-pixel shifts are
exact (see fsof_torch/evaluation/warp.py); the first table prints what that costs. The second, at
KITTI's size without gradient (evaluation): each kind of ``photometric_error_map`` (the warp included) and
``photometric_error_maps`` with L1, SSIM and census at once (one warp), with the ratio to the
warp. Single thread, warm-up, median of repeats, milliseconds. Run: python benchmarks/bench_warp.py
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from fsof_torch.evaluation.photometric import photometric_error_map, photometric_error_maps
from fsof_torch.evaluation.warp import normalize_coordinates, warp_backward


def kornia_bilinear(image, flow):
    from kornia.geometry.transform import remap

    B, _, H, W = image.shape
    u = torch.arange(W, dtype=flow.dtype).expand(H, W)
    v = torch.arange(H, dtype=flow.dtype).unsqueeze(1).expand(H, W)
    x = normalize_coordinates(u + flow[:, 0], W, align_corners=True)
    y = normalize_coordinates(v + flow[:, 1], H, align_corners=True)
    return remap(image, x, y, mode="bilinear", align_corners=True, normalized_coordinates=True)


def median_ms(fn, repeats=7, warmup=2):
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    from cli import description

    argparse.ArgumentParser(description=description(__doc__)).parse_args(argv)
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    print(f"{'size':>16} {'pass':>9} {'warp_backward':>14} {'kornia remap':>13} {'ratio':>6}")
    for B, H, W in [(1, 64, 160), (1, 375, 1242), (4, 128, 416)]:
        image = torch.rand(B, 3, H, W, generator=g) * 255
        flow = torch.randn(B, 2, H, W, generator=g) * 3
        for name, grad in (("forward", False), ("fwd+bwd", True)):
            def run(f):
                im = image.clone().requires_grad_(grad)
                fl = flow.clone().requires_grad_(grad)
                if grad:
                    out = f(im, fl)
                    out = out[0] if isinstance(out, tuple) else out
                    out.sum().backward()
                else:
                    with torch.no_grad():
                        f(im, fl)
            ours = median_ms(lambda: run(warp_backward))
            ref = median_ms(lambda: run(kornia_bilinear))
            print(f"{f'{B}x3x{H}x{W}':>16} {name:>9} {ours:>11.2f} ms {ref:>10.2f} ms {ours / ref:>6.1f}")
    photometric_table(g)
    return 0


def photometric_table(g: torch.Generator) -> None:
    B, H, W = 1, 375, 1242
    image1 = torch.rand(B, 3, H, W, generator=g) * 255
    image2 = torch.rand(B, 3, H, W, generator=g) * 255
    flow = torch.randn(B, 2, H, W, generator=g) * 3
    with torch.no_grad():
        ref = median_ms(lambda: warp_backward(image2, flow))
        rows = [("warp_backward", ref)]
        for kind in ("l1", "ssim", "census", "soft_census"):
            rows.append((f"kind={kind!r}", median_ms(lambda: photometric_error_map(image1, image2, flow, kind=kind))))
        rows.append(("l1+ssim+census", median_ms(lambda: photometric_error_maps(image1, image2, flow))))
    print(f"\nphotometric error, {B}x3x{H}x{W}, no gradient")
    print(f"{'what':>22} {'ms':>9} {'/ warp':>7}")
    for name, ms in rows:
        print(f"{name:>22} {ms:>9.1f} {ms / ref:>7.1f}")


if __name__ == "__main__":
    raise SystemExit(main())
