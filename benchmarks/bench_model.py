"""Speed of the freespace flow models against the paper's NumPy formula and a fill floor.

Measures, in one run, at one image size (default KITTI 1242×375), float32, on the CPU:

- ``displacement_flow`` and ``velocity_flow`` eager, and compiled with ``torch.compile(fullgraph=True)``
  (skipped with ``--no-compile`` or when compiling fails here);
- the speed paths of the library, each against what it replaces: ``flow_from_map`` in place
  (eager, without autograd: the default there) against its general path (the one autograd and
  tracing use), on the same maps, and against itself computing every row (on the CPU it computes
  only the band of rows that can hold a valid pixel); and the compiled model against the same graph with its last
  step, the opaque uint8 -> bool op, replaced by a plain cast;
- a plain NumPy float64 transcription of the paper's λ formula (eq. 13, per pixel, as the official
  code does), one frame after another;
- the floor: ``torch.full`` of a (B, 2, H, W) float32 tensor, the output the model must at least
  write (and, for reference, the same plus the (B, 1, H, W) bool mask the model also returns).

Each row: median over ``--repeats`` timed calls after warm-up, in ms per frame and frames per
second, the fastest call (a steadier figure on a shared machine), the minor page faults per call (fresh memory from the OS; on CPU these often dominate
eager timings), and the ratios to the NumPy formula and to the floor.

Usage::

    python benchmarks/bench_model.py                      # 1 thread, batch 1 and 8
    python benchmarks/bench_model.py --threads 2 --repeats 50 --json bench.json
"""

from __future__ import annotations

import argparse
import math
import platform
import resource
import statistics
import sys
import time

import numpy as np
import torch

from fsof_torch.geometry.camera import Camera
from fsof_torch.geometry import road_flow
from fsof_torch.geometry.road_flow import DisplacementFlow, VelocityFlow, displacement_flow, flow_from_map, velocity_flow
from fsof_torch.geometry.road_models import ROAD_MODELS, pack_params

# KITTI 2015 left colour camera (P_rect_02), nominal height; a mounting and a motion with every
# term of the model non-zero.
K_KITTI = [[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]]
HEIGHT, ROLL, PITCH = 1.65, 0.01, 0.0
X_D, Z_D, YAW = 0.05, 1.2, 0.01
SPEED, STEERING, WHEELBASE = 12.0, 0.02, 2.7


def paper_formula_numpy(fx: float, fy: float, cx: float, cy: float, h: float, roll: float,
                        x_d: np.ndarray, z_d: np.ndarray, yaw: np.ndarray, size: tuple[int, int]):
    """The paper's eq. 13 in NumPy float64, frame by frame: flow (B, 2, H, W), valid (B, 1, H, W)."""
    H, W = size
    v, u = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    st, ct = math.sin(roll), math.cos(roll)
    flows, valids = [], []
    for xd, zd, phi in zip(x_d, z_d, yaw):
        lam1 = (u - cx) / fx * st + (v - cy) / fy * ct
        lam2 = (u - cx) / fx * ct - (v - cy) / fy * st
        lam3 = lam2 * h - lam1 * xd
        lam4 = h - lam1 * zd
        sp, cp = math.sin(phi), math.cos(phi)
        D = lam3 * sp + lam4 * cp
        valid = (lam1 > 0) & (D > 0)
        Ds = np.where(valid, D, 1.0)
        a = (lam3 * cp - lam4 * sp) / Ds - lam2
        b = lam1 * h / Ds - lam1
        fu = np.where(valid, fx * ct * a + fx * st * b, 0.0)
        fv = np.where(valid, -fy * st * a + fy * ct * b, 0.0)
        flows.append(np.stack([fu, fv]))
        valids.append(valid[None])
    return np.stack(flows), np.stack(valids)


def _time(fn, repeats: int, warmup: int) -> tuple[float, float, float]:
    """Median and fastest seconds per call, and minor page faults per call."""
    for _ in range(warmup):
        fn()
    times = []
    faults0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults0) / repeats
    return statistics.median(times), min(times), faults


def run(args: argparse.Namespace) -> dict:
    torch.set_num_threads(args.threads)
    H, W = args.size
    size = (H, W)
    rows: list[dict] = []
    compile_status = "skipped (--no-compile)" if args.no_compile else "ok"
    for B in args.batch:
        cam = Camera(torch.tensor(K_KITTI, dtype=torch.float32), HEIGHT, ROLL, PITCH).expand(B)
        x_d = torch.full((B,), X_D)
        z_d = torch.linspace(0.8, 1.6, B) if B > 1 else torch.full((1,), Z_D)
        yaw = torch.full((B,), YAW)
        speed, steering = torch.full((B,), SPEED), torch.full((B,), STEERING)

        def measure(cases):
            for name, fn in cases:
                repeats = max(3, args.repeats // 4) if name.startswith("NumPy") else args.repeats
                sec, best, faults = _time(fn, repeats, args.warmup)
                rows.append(dict(name=name, batch=B, ms_per_frame=sec * 1e3 / B, fps=B / sec,
                                 best_ms_per_frame=best * 1e3 / B, faults_per_call=faults, repeats=repeats))

        # Eager first, before torch.compile has touched the allocator: what a fresh process sees.
        measure([("displacement_flow eager", lambda: displacement_flow(cam, x_d, z_d, yaw, size)),
                 ("velocity_flow eager", lambda: velocity_flow(cam, speed, steering, WHEELBASE, size))])
        # flow_from_map's paths on the same maps: in place (no autograd) and general (a map that
        # requires grad takes it; under no_grad no graph is kept)
        model = ROAD_MODELS["paper"]
        cam_p, values = pack_params(model, cam, {"x_d": x_d, "z_d": z_d, "yaw": yaw})
        M, horizon = model.matrix(cam_p, values), model.horizon_row(cam_p, values)
        M_general = M.clone().requires_grad_()
        with torch.no_grad():
            measure([("flow_from_map in place", lambda: flow_from_map(M, horizon, size))])
            # the in-place path computing every row (as off the CPU), without its band of rows
            # that can hold a valid pixel (measured while it is replaced)
            band = road_flow._valid_rows
            road_flow._valid_rows = lambda *args: None
            try:
                measure([("flow_from_map in place, every row", lambda: flow_from_map(M, horizon, size))])
            finally:
                road_flow._valid_rows = band
            measure([("flow_from_map general path", lambda: flow_from_map(M_general, horizon, size))])
        if not args.no_compile:
            try:
                disp_c = torch.compile(DisplacementFlow(size), fullgraph=True, dynamic=False)
                vel_c = torch.compile(VelocityFlow(size, WHEELBASE), fullgraph=True, dynamic=False)
                t0 = time.perf_counter()
                got, got_valid = disp_c(cam, x_d, z_d, yaw)
                vel_c(cam, speed, steering)
                compile_s = time.perf_counter() - t0
                want, want_valid = displacement_flow(cam, x_d, z_d, yaw, size)
                if not torch.equal(got_valid, want_valid) or not torch.allclose(got, want, atol=1e-3):
                    raise RuntimeError("compiled result differs from eager")
                print(f"batch {B}: torch.compile of both models took {compile_s:.1f} s", file=sys.stderr)
                measure([("displacement_flow compiled", lambda: disp_c(cam, x_d, z_d, yaw)),
                         ("velocity_flow compiled", lambda: vel_c(cam, speed, steering))])
                # the same graph with a plain cast as its last step (measured while it is in place:
                # the compiled graph guards on the function it traced)
                opaque = road_flow._uint8_to_bool
                road_flow._uint8_to_bool = lambda mask: mask.bool()
                try:
                    disp_plain = torch.compile(DisplacementFlow(size), fullgraph=True, dynamic=False)
                    disp_plain(cam, x_d, z_d, yaw)
                    measure([("compiled, plain bool cast", lambda: disp_plain(cam, x_d, z_d, yaw))])
                finally:
                    road_flow._uint8_to_bool = opaque
            except Exception as err:  # noqa: BLE001 - report and go on without the compiled rows
                compile_status = f"failed: {type(err).__name__}: {err}"[:200]
                print(f"torch.compile unavailable here ({compile_status})", file=sys.stderr)
        xd_np, zd_np, yaw_np = (t.double().numpy() for t in (x_d, z_d, yaw))
        K = K_KITTI
        measure([
            ("NumPy paper formula (float64)",
             lambda: paper_formula_numpy(K[0][0], K[1][1], K[0][2], K[1][2], HEIGHT, ROLL, xd_np, zd_np,
                                         yaw_np, size)),
            ("floor: torch.full (B,2,H,W)", lambda: torch.full((B, 2, H, W), 1.0)),
            ("floor: flow + bool mask", lambda: (torch.full((B, 2, H, W), 1.0),
                                                 torch.full((B, 1, H, W), True))),
        ])
    for B in args.batch:
        at_b = {r["name"]: r for r in rows if r["batch"] == B}
        numpy_ms = at_b["NumPy paper formula (float64)"]["ms_per_frame"]
        floor_ms = at_b["floor: torch.full (B,2,H,W)"]["ms_per_frame"]
        for r in at_b.values():
            r["speedup_vs_numpy"] = numpy_ms / r["ms_per_frame"]
            r["x_floor"] = r["ms_per_frame"] / floor_ms
    return dict(size=[H, W], dtype="float32", threads=args.threads, batches=args.batch,
                torch=torch.__version__, numpy=np.__version__, python=platform.python_version(),
                machine=platform.machine(), processor=_cpu_name(), compile=compile_status, rows=rows)


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def print_table(result: dict) -> None:
    H, W = result["size"]
    print(f"fsof-torch model speed: {W}x{H}, {result['dtype']}, {result['threads']} thread(s), "
          f"torch {result['torch']}, {result['processor']}; torch.compile: {result['compile']}")
    head = (f"{'B':>2}  {'what':<32} {'ms/frame':>9} {'frames/s':>9} {'best ms':>8} {'faults':>7} "
            f"{'vs NumPy':>9} {'x floor':>8}")
    print(head)
    print("-" * len(head))
    for r in result["rows"]:
        print(f"{r['batch']:>2}  {r['name']:<32} {r['ms_per_frame']:>9.3f} {r['fps']:>9.1f} "
              f"{r['best_ms_per_frame']:>8.3f} "
              f"{r['faults_per_call']:>7.0f} {r['speedup_vs_numpy']:>8.1f}x {r['x_floor']:>7.1f}x")
    print("ms/frame and frames/s: medians; best ms: the fastest call (per frame); vs NumPy: how many "
          "times faster than the NumPy float64 paper formula (higher is better); x floor: time / time of "
          "torch.full of the (B,2,H,W) output (lower is better); faults: minor page faults per call.")


def main(argv: list[str] | None = None) -> int:
    from cli import description, json_path, nonnegative_int, positive_int, thread_count, write_json

    parser = argparse.ArgumentParser(description=description(__doc__))
    parser.add_argument("--threads", type=thread_count, default=1,
                        help="torch threads, at most this machine's CPUs (default 1)")
    parser.add_argument("--repeats", type=positive_int, default=40, help="timed calls per row (default 40)")
    parser.add_argument("--warmup", type=nonnegative_int, default=3, help="untimed calls first (default 3)")
    parser.add_argument("--batch", type=positive_int, nargs="+", default=[1, 8],
                        help="batch sizes, each once (default 1 8)")
    parser.add_argument("--size", type=positive_int, nargs=2, default=[375, 1242], metavar=("H", "W"),
                        help="image size (default 375 1242)")
    parser.add_argument("--no-compile", action="store_true", help="skip the torch.compile rows")
    parser.add_argument("--json", metavar="PATH",
                        help="also write the results as JSON (an earlier file there is removed at the start)")
    args = parser.parse_args(argv)
    if len(set(args.batch)) < len(args.batch):
        parser.error(f"--batch: expected distinct batch sizes, got {' '.join(map(str, args.batch))}")
    args.json = json_path(parser, args.json)
    result = run(args)
    print_table(result)
    if args.json is not None:
        write_json(args.json, result)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
