"""Speed of fitting the road-motion models to one frame of flow, and to a batch of 8.

Data: a KITTI-sized frame (375 × 1242, the KITTI camera), road flow of a known motion with
roll plus Gaussian noise (σ = 0.5 px), 10% of the mask replaced by the flow of another motion
(a car), and a mask of about 120 000 pixels below the horizon (the size the issue names: the
official code's scipy ``curve_fit`` took 0.77 s on it).

Rows (single thread, warm-up then repeats, median and min wall ms, median process CPU ms):
- ``fit_displacement`` with its default subsample (``max_points=8192``) and with every mask
  pixel (``max_points=None``), one frame and a batch of 8;
- ``fit_road`` with ``model="plane"`` (8 parameters: the 6-DOF motion and the camera's attitude)
  and ``model="homography"`` on the same frame;
- SciPy ``least_squares(loss="soft_l1")`` on the same 120 000 pixels (the same homography
  model, vectorised NumPy residuals, 2-point Jacobian) — the reference, measured in this run;
- SciPy ``curve_fit`` (plain least squares, the official code's call) with the paper's λ form
  (eq. 13) as the model function, unless ``--no-curve-fit``.

``--baseline REV`` (default 09d064e, the flat package before the road-model family and the
one solver; ``none`` to skip): that git revision's package is imported beside the current one
(``baseline.py``) and its ``fit_displacement`` is timed interleaved call by call with the
current one (the same load on a shared machine), for the default subsample, one frame and a
batch of 8; the rows report both, their ratio and the largest parameter difference.

After the table: the host reads of one call of each fit on the single frame, counted with
torch.profiler (``aten::_local_scalar_dense``: ``.item()`` / ``bool(tensor)``; ``aten::nonzero``,
which reads its result's size; ``aten::linalg_solve``, which reads its error code).

Usage: ``python benchmarks/bench_fit.py [--repeats 10] [--json out.json] [--no-curve-fit]
[--baseline REV]``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

# one thread for the NumPy / SciPy reference too: BLAS reads these when it is loaded (setting
# them later, in main(), left the reference on two threads)
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from baseline import DEFAULT_BASELINE, load_baseline  # noqa: E402
from fsof_torch.geometry.camera import Camera  # noqa: E402
from fsof_torch.estimation.flow_fit import fit_displacement, fit_road  # noqa: E402
from fsof_torch.geometry.road_flow import displacement_flow  # noqa: E402

SIZE = (375, 1242)
K = [[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]]
TRUTH = dict(x_d=0.05, z_d=1.1, yaw=0.02, roll=0.01)


def make_frame(seed: int, dtype=torch.float32):
    cam = Camera(torch.tensor(K, dtype=torch.float64), 1.65, TRUTH["roll"])
    g = torch.Generator().manual_seed(seed)
    jitter = 1.0 + 0.05 * (torch.rand(1, generator=g, dtype=torch.float64).item() - 0.5)
    flow, valid = displacement_flow(cam, TRUTH["x_d"], TRUTH["z_d"] * jitter, TRUTH["yaw"], SIZE)
    car, _ = displacement_flow(cam, -0.2, 0.4, 0.0, SIZE)
    flow = flow.clone()
    flow[..., 300:420] = car[..., 300:420]
    flow = flow + 0.5 * torch.randn(flow.shape, generator=g, dtype=flow.dtype)
    mask = valid.clone()
    mask[:, :, :278] = False  # about 120 000 pixels
    return flow.to(dtype), mask


def timed(fn, repeats: int, warmup: int = 2) -> tuple[float, float, float]:
    """Median and min wall ms, and median process CPU ms (less sensitive to a loaded machine)."""
    for _ in range(warmup):
        fn()
    times, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
        cpu.append((time.process_time() - c) * 1e3)
    return statistics.median(times), min(times), statistics.median(cpu)


def timed_pair(fn_a, fn_b, repeats: int, warmup: int = 2):
    """:func:`timed` for two functions, alternating calls so that both see the same load."""
    for _ in range(warmup):
        fn_a()
        fn_b()
    out = {"a": ([], []), "b": ([], [])}
    for _ in range(repeats):
        for key, fn in (("a", fn_a), ("b", fn_b)):
            t, c = time.perf_counter(), time.process_time()
            fn()
            out[key][0].append((time.perf_counter() - t) * 1e3)
            out[key][1].append((time.process_time() - c) * 1e3)
    return [(statistics.median(w), min(w), statistics.median(c)) for w, c in out.values()]


HOST_READS = ("aten::_local_scalar_dense", "aten::nonzero", "aten::linalg_solve")


def host_reads(fn) -> dict[str, int]:
    """Host reads of one call of ``fn``, by kind, counted with torch.profiler."""
    from torch.profiler import ProfilerActivity, profile

    fn()  # constants cached on the first call
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    counts = dict.fromkeys(HOST_READS, 0)
    for event in prof.events():
        if event.name in counts:
            counts[event.name] += 1
    return counts


def scipy_problem(flow: torch.Tensor, mask: torch.Tensor):
    """Pixels, targets and a vectorised residual of the same homography model for SciPy."""
    m = mask[0, 0].numpy()
    v, u = np.nonzero(m)
    target = flow[0].double().numpy()[:, v, u]
    Kn = np.asarray(K)
    Kinv = np.linalg.inv(Kn)
    h = 1.65
    p = np.stack([u, v, np.ones_like(u)]).astype(np.float64)

    def residual(x):
        xd, zd, yaw, roll = x
        c, s = np.cos(yaw), np.sin(yaw)
        inner = np.array([[c, -(c * xd - s * zd) / h, -s], [0, 1, 0], [s, -(s * xd + c * zd) / h, c]])
        cr, sr = np.cos(roll), np.sin(roll)
        R = np.array([[cr, sr, 0], [-sr, cr, 0], [0, 0, 1]])
        Hm = Kn @ R @ inner @ R.T @ Kinv
        q = Hm @ p
        f = q[:2] / q[2] - p[:2]
        return (f - target).ravel()

    return residual, u.astype(np.float64), v.astype(np.float64), target


def paper_flow(uv, roll, xd, zd, yaw, h=1.65):
    """The paper's eq. 13 (λ form) for curve_fit: returns the stacked (u, v) flow."""
    fx, fy, u0, v0 = K[0][0], K[1][1], K[0][2], K[1][2]
    u, v = uv
    st, ct = np.sin(roll), np.cos(roll)
    l1 = (u - u0) / fx * st + (v - v0) / fy * ct
    l2 = (u - u0) / fx * ct - (v - v0) / fy * st
    l3 = l2 * h - l1 * xd
    l4 = h - l1 * zd
    D = l3 * np.sin(yaw) + l4 * np.cos(yaw)
    a = (l3 * np.cos(yaw) - l4 * np.sin(yaw)) / D - l2
    b = l1 * h / D - l1
    fu = fx * ct * a + fx * st * b
    fv = -fy * st * a + fy * ct * b
    return np.concatenate([fu, fv])


def main(argv: list[str] | None = None) -> int:
    from cli import baseline_revision, description, json_path, positive_int, write_json

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--repeats", type=positive_int, default=10, help="timed calls per row (default 10)")
    parser.add_argument("--json", type=str, default=None, metavar="PATH",
                        help="write the rows as JSON here (an earlier file there is removed at the start)")
    parser.add_argument("--no-curve-fit", action="store_true", help="skip the curve_fit row")
    parser.add_argument("--baseline", type=str, default=None, metavar="REV",
                        help="a git revision whose fit_displacement is timed interleaved with the current one "
                             f"(default {DEFAULT_BASELINE}, left out where git or it is unavailable; 'none' to skip)")
    args = parser.parse_args(argv)
    args.baseline = baseline_revision(parser, args.baseline, DEFAULT_BASELINE)
    args.json = json_path(parser, args.json)
    torch.set_num_threads(1)

    from scipy.optimize import curve_fit, least_squares

    flow, mask = make_frame(0)
    cam = Camera(torch.tensor(K, dtype=torch.float32), 1.65)
    frames = [make_frame(i) for i in range(8)]
    flow8 = torch.cat([f for f, _ in frames])
    mask8 = torch.cat([m for _, m in frames])
    n_pixels = int(mask.sum())

    rows = []

    def add(name, fn, repeats, frames_=1, check=None):
        med, best, cpu = timed(fn, repeats)
        row = dict(name=name, frames=frames_, median_ms=round(med, 2), min_ms=round(best, 2),
                   cpu_ms=round(cpu, 2))
        if check is not None:
            row.update(check)
        rows.append(row)

    fit = fit_displacement(flow, mask, cam)
    add("fit_displacement (max_points=8192)", lambda: fit_displacement(flow, mask, cam), args.repeats,
        check=dict(z_d=round(float(fit.z_d), 5), roll=round(float(fit.roll), 5), success=bool(fit.success)))
    fit = fit_displacement(flow, mask, cam, max_points=None)
    add("fit_displacement (all pixels)", lambda: fit_displacement(flow, mask, cam, max_points=None),
        args.repeats, check=dict(z_d=round(float(fit.z_d), 5), roll=round(float(fit.roll), 5),
                                 success=bool(fit.success)))
    fit8 = fit_displacement(flow8, mask8, cam)
    add("fit_displacement batch 8 (max_points=8192)", lambda: fit_displacement(flow8, mask8, cam),
        args.repeats, 8, check=dict(success=int(fit8.success.sum())))
    add("fit_displacement batch 8 (all pixels)",
        lambda: fit_displacement(flow8, mask8, cam, max_points=None), max(3, args.repeats // 2), 8)

    for model in ("plane", "homography"):
        fit = fit_road(flow, mask, cam, model=model)
        check = dict(success=bool(fit.success))
        if model == "plane":
            check.update(z_d=round(float(fit.z_d), 5), roll=round(float(fit.roll), 5))
        add(f"fit_road model={model!r} (max_points=8192)", lambda: fit_road(flow, mask, cam, model=model),
            args.repeats, check=check)

    if args.baseline is not None:
        base = load_baseline(args.baseline)
        base_cam = base.Camera(torch.tensor(K, dtype=torch.float32), 1.65)
        for label, (f, m, frames_) in {"1 frame": (flow, mask, 1), "batch 8": (flow8, mask8, 8)}.items():
            res_a, res_b = base.fit_displacement(f, m, base_cam), fit_displacement(f, m, cam)
            diff = max(float((getattr(res_a, k) - getattr(res_b, k)).abs().max())
                       for k in ("x_d", "z_d", "yaw", "roll", "pitch"))
            (med_a, min_a, cpu_a), (med_b, min_b, cpu_b) = timed_pair(
                lambda: base.fit_displacement(f, m, base_cam), lambda: fit_displacement(f, m, cam), args.repeats)
            for name, med, best, cpu in ((f"baseline {args.baseline}", med_a, min_a, cpu_a),
                                         ("current", med_b, min_b, cpu_b)):
                rows.append(dict(name=f"{name}, {label} (interleaved)", frames=frames_,
                                 median_ms=round(med, 2), min_ms=round(best, 2), cpu_ms=round(cpu, 2),
                                 max_param_diff=float(f"{diff:.3g}")))
            rows[-1].update(vs_baseline_median=round(med_b / med_a, 3), vs_baseline_min=round(min_b / min_a, 3))

    residual, u, v, target = scipy_problem(flow, mask)
    x0 = np.array([0.0, 0.5, 0.0, 0.0])
    sol = least_squares(residual, x0, loss="soft_l1", f_scale=1.0)
    add("scipy least_squares soft_l1 (all pixels)",
        lambda: least_squares(residual, x0, loss="soft_l1", f_scale=1.0), max(3, args.repeats // 3),
        check=dict(z_d=round(float(sol.x[1]), 5), roll=round(float(sol.x[3]), 5), success=bool(sol.success)))
    if not args.no_curve_fit:
        ydata = np.concatenate([target[0], target[1]])
        p0 = [0.0, 0.0, 0.5, 0.0]
        popt, _ = curve_fit(paper_flow, (u, v), ydata, p0=p0)
        add("scipy curve_fit, paper eq. 13 (all pixels)",
            lambda: curve_fit(paper_flow, (u, v), ydata, p0=p0), max(3, args.repeats // 3),
            check=dict(z_d=round(float(popt[2]), 5), roll=round(float(popt[0]), 5)))

    ref = next(r["median_ms"] for r in rows if r["name"].startswith("scipy least_squares"))
    for r in rows:
        r["scipy_ls_ratio"] = round(ref / r["median_ms"] * r["frames"], 1)

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"fit benchmark: {n_pixels} mask pixels, frame {SIZE[0]}x{SIZE[1]}, 1 thread, "
          f"torch {torch.__version__}, load average {load:.1f} on {os.cpu_count()} CPUs")
    g = torch.Generator().manual_seed(0)  # frame 0's z_d, as make_frame draws it
    z0 = TRUTH["z_d"] * (1.0 + 0.05 * (torch.rand(1, generator=g, dtype=torch.float64).item() - 0.5))
    print(f"truth of the single frame: z_d = {z0:.5f}, roll = {TRUTH['roll']}, x_d = {TRUTH['x_d']}, "
          f"yaw = {TRUTH['yaw']} (batch frames: z_d within ±2.5%)")
    header = (f"{'method':<46} {'frames':>6} {'median ms':>10} {'min ms':>8} {'cpu ms':>8} "
              f"{'speed-up vs scipy/frame':>24}  check")
    print(header)
    print("-" * len(header))
    for r in rows:
        extra = {k: v for k, v in r.items()
                 if k not in ("name", "frames", "median_ms", "min_ms", "cpu_ms", "scipy_ls_ratio")}
        print(f"{r['name']:<46} {r['frames']:>6} {r['median_ms']:>10.2f} {r['min_ms']:>8.2f} {r['cpu_ms']:>8.2f} "
              f"{r['scipy_ls_ratio']:>23.1f}x  {extra}")
    ratios = [(r["name"].split(", ")[1].split(" (")[0], r["vs_baseline_median"], r["vs_baseline_min"])
              for r in rows if "vs_baseline_median" in r]
    if ratios:
        print(f"current / baseline {args.baseline} (interleaved): "
              + "; ".join(f"{label}: median {a:.3f}, min {b:.3f}" for label, a, b in ratios))
    reads = {"fit_displacement": host_reads(lambda: fit_displacement(flow, mask, cam)),
             "fit_displacement batch 8": host_reads(lambda: fit_displacement(flow8, mask8, cam)),
             "fit_road plane": host_reads(lambda: fit_road(flow, mask, cam, model="plane")),
             "fit_road homography": host_reads(lambda: fit_road(flow, mask, cam, model="homography"))}
    print("host reads per call (torch.profiler):")
    for name, counts in reads.items():
        kinds = ", ".join(f"{kind.removeprefix('aten::')} {n}" for kind, n in counts.items())
        print(f"  {name:<26} {sum(counts.values()):>3}  ({kinds})")
    if args.json is not None:
        write_json(args.json, dict(n_pixels=n_pixels, size=SIZE, load_average=load, rows=rows, host_reads=reads))
    return 0


if __name__ == "__main__":
    sys.exit(main())
