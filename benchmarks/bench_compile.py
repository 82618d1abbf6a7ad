"""torch.compile of FreespaceRefiner against eager (the reference), per way of finding the motion.

For B = 2 rendered pairs (the "default" scene at 64 x 192, as tests/test_fusion_backends.py):
the first compiled call (tracing and code generation included), a later compiled call, the eager
call, their ratio, the largest difference from eager in pixels, and how many graphs dynamo
captured (estimation runs eagerly outside them: it is iterative and data dependent). Single
thread (torch and OpenCV); eager and later calls are the median of repeats, milliseconds.

Run: python benchmarks/bench_compile.py [--backend inductor|aot_eager|eager] [--cold]
(--cold: an empty inductor cache, as on a first run, removed when the run ends; otherwise kernels
cached by earlier runs are reused and the first call is faster).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
import warnings


def main(argv: list[str] | None = None) -> int:
    from cli import description, positive_int

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--backend", default="inductor", choices=["inductor", "aot_eager", "eager"],
                        help="torch.compile's backend (default inductor)")
    parser.add_argument("--cold", action="store_true", help="start from an empty inductor cache")
    parser.add_argument("--repeats", type=positive_int, default=5,
                        help="timed calls for the eager and later compiled medians (default 5)")
    args = parser.parse_args(argv)
    if not args.cold:
        return run(args)
    cache = tempfile.mkdtemp(prefix="fsof_inductor_")
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = cache  # (before torch reads its configuration)
    try:
        return run(args)
    finally:
        shutil.rmtree(cache, ignore_errors=True)  # (tens of MB of kernels, of no use to a later cold run)


def run(args: argparse.Namespace) -> int:
    import torch
    from torch._dynamo.utils import counters

    from fsof_torch.data.scene import render_pair
    from fsof_torch.refinement.fusion import FreespaceRefiner

    import cv2

    torch.set_num_threads(1)
    cv2.setNumThreads(1)  # (the image estimator's blur and pyramids run in OpenCV)
    warnings.simplefilter("ignore")
    pairs = [render_pair("default", i, size=(64, 192), noise=0.0) for i in range(2)]
    gt = torch.stack([p["flow"] for p in pairs])
    road = torch.stack([p["road"] for p in pairs])
    images = (torch.stack([p["image1"] for p in pairs]), torch.stack([p["image2"] for p in pairs]))
    rows = torch.arange(64).reshape(1, 1, -1, 1)
    g = torch.Generator().manual_seed(0)
    pred = (gt * torch.where(rows > 45, 0.6, 1.0) + 0.3 * torch.randn(gt.shape, generator=g)).float()
    odo = {k: torch.tensor([p["odometry"][k] for p in pairs]) for k in ("x_d", "z_d", "yaw")}
    cam = pairs[0]["camera"]
    cases = {"odometry": (odo, None), "flow fit": (None, None), "images": (None, images),
             "odometry+images": (odo, images)}

    def median_ms(fn) -> float:
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
        return statistics.median(times)

    print(f"backend {args.backend}, {'cold' if args.cold else 'warm'} cache, torch {torch.__version__}, B=2, 64x192")
    print(f"{'motion from':>16} {'first call':>11} {'compiled':>10} {'eager':>9} {'ratio':>6} {'max diff px':>12} {'graphs':>7}")
    for name, (odometry, ims) in cases.items():
        eager_refiner = FreespaceRefiner()
        eager = eager_refiner(pred, road, cam, odometry, images=ims)
        eager_ms = median_ms(lambda: eager_refiner(pred, road, cam, odometry, images=ims))
        torch._dynamo.reset()
        counters.clear()
        compiled_refiner = torch.compile(FreespaceRefiner(), backend=args.backend)
        t0 = time.perf_counter()
        out = compiled_refiner(pred, road, cam, odometry, images=ims)
        first_s = time.perf_counter() - t0
        graphs = counters["stats"]["unique_graphs"]
        compiled_ms = median_ms(lambda: compiled_refiner(pred, road, cam, odometry, images=ims))
        diff = (out.flow - eager.flow).abs().max().item()
        print(f"{name:>16} {first_s:>9.1f} s {compiled_ms:>7.1f} ms {eager_ms:>6.1f} ms "
              f"{compiled_ms / eager_ms:>6.2f} {diff:>12.1e} {graphs:>7}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
