"""``python -m eval synth``: render a synthetic driving sequence with exact ground truth and write
it to disk in the KITTI-like layout of :mod:`fsof_torch.io.layout` (read it back with
:class:`fsof_torch.data.datasets.SyntheticFlowDataset`).

Example::

    python -m eval synth --preset default --pairs 4 --out runs/synth --size 188 621 --seed 0
"""

from __future__ import annotations

import argparse
import math
import sys

import torch

from .paths import MAX_SIDE, file_path, given_path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="default", help="scene preset (fsof_torch.data.scene.PRESETS); default: default")
    from fsof_torch.data.scene.render import MAX_FRAME

    parser.add_argument("--pairs", type=int, default=4, metavar="N",
                        help=f"number of frame pairs, 1 to {MAX_FRAME} (default 4)")
    parser.add_argument("--out", required=True, type=given_path, metavar="DIR",
                        help="output folder: a new or empty one (created); a folder holding files is refused")
    parser.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), default=None,
                        help=f"image size, each side at most {MAX_SIDE} (default: the preset's)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the scene (default 0)")
    parser.add_argument("--float64", action="store_true", help="render in float64 (slower; flow is stored to 1/64 px anyway)")
    parser.add_argument("--json", type=file_path, default=None, metavar="PATH", help="also write the summary as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


class _Unstorable(Exception):
    """A rendered pair whose ground truth the layout's files cannot hold (the message says why)."""


def _stats(pair: dict) -> dict:
    flow, valid = pair["flow"], pair["valid"]
    road = pair.get("road")
    odo = pair["odometry"]
    magnitude = flow.norm(dim=0, keepdim=True)[valid]
    pose = pair.get("road_pose")
    return {
        "x_d": float(odo["x_d"]), "z_d": float(odo["z_d"]), "yaw_deg": math.degrees(float(odo["yaw"])),
        "valid_pct": 100.0 * float(valid.float().mean()),
        "road_pct": 100.0 * float(road.float().mean()) if road is not None else None,
        "max_flow_px": float(magnitude.max()) if magnitude.numel() else 0.0,
        # the camera over the road at t (differs from the calibration with body motion or a grade)
        "road_pose": {k: float(v) for k, v in pose.items()} if pose is not None else None,
    }


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def run(args: argparse.Namespace) -> int:
    from fsof_torch.io import write_json, write_synthetic_sequence
    from fsof_torch.io.kitti import check_kitti_flow_range
    from fsof_torch.data.scene import PRESETS, render_pair

    from .paths import bad_file, bad_folder, bad_size, first_bad, make_parent, other_run_above, remove_outputs
    from .provenance import environment

    if args.preset not in PRESETS:
        print(f"error: --preset: unknown preset {args.preset!r}; choose from {', '.join(sorted(PRESETS))}", file=sys.stderr)
        return 2
    from fsof_torch.data.scene.render import MAX_FRAME

    if not 1 <= args.pairs <= MAX_FRAME:  # (the scenes' frames end at MAX_FRAME)
        print(f"error: --pairs: expected 1 to {MAX_FRAME}, got {args.pairs}", file=sys.stderr)
        return 2
    size = tuple(args.size) if args.size is not None else None
    if size is not None and min(size) <= 0:
        print(f"error: --size: expected positive H W, got {args.size}", file=sys.stderr)
        return 2
    bad = first_bad(bad_size(size, "--size"), bad_folder(args.out, "--out"), bad_file(args.json, "--json", args.out),
                    other_run_above(args.json) if args.json is not None else None)
    if bad is None and args.json is not None and args.json.resolve().is_relative_to(args.out.resolve()):
        # the layout's files (poses.txt, meta.json, ...) would replace it, or it one of them
        bad = f"--json: {str(args.json)!r} is inside --out {str(args.out)!r}, which the job fills; give a path outside it"
    if bad is None and args.out.is_dir() and any(args.out.iterdir()):
        held = sorted(p.name for p in args.out.iterdir())
        # pairs of an older, longer run would stay beside the new ones and be read back with them
        listed = ", ".join(held[:4]) + (", ..." if len(held) > 4 else "")
        bad = f"--out: {str(args.out)!r} already holds files ({listed}); give a new or empty folder"
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    if args.json is not None:  # an earlier run's JSON there goes: a run that stops would leave it as its own
        remove_outputs(args.json.parent, [args.json.name])
    from fsof_torch.data.scene import scene_config
    from fsof_torch.data.scene.world import Scene

    dtype = torch.float64 if args.float64 else torch.float32
    rows: list[dict] = []
    # the scene's float64 camera, which a float32 render rounds: the files keep its digits (a
    # float32 reader rounds them as the render did), as SceneDataset(camera_dtype=torch.float64) gives it
    camera64 = Scene(scene_config(args.preset, **({} if size is None else {"size": size})), args.seed,
                     torch.float64).camera64

    def rendered():
        for index in range(args.pairs):
            pair = render_pair(args.preset, index, seed=args.seed, size=size, dtype=dtype)
            try:  # (larger images, larger flow: a large --size can exceed what flow_occ/ holds)
                check_kitti_flow_range(pair["flow"], pair["valid"][0], "flow")
            except ValueError as err:
                kept = "nothing was written" if index == 0 else (
                    f"pairs 0 to {index - 1} are written to {str(args.out)!r} without meta.json (an incomplete "
                    f"sequence): give a new or empty --out")
                raise _Unstorable(f"--size: pair {index}'s ground-truth {err}; give a smaller --size ({kept})") from None
            rows.append({"index": index, **_stats(pair)})
            yield {**pair, "camera": camera64.to(torch.float64, copy=True)}

    meta = {"preset": args.preset, "seed": args.seed, "requested_size": list(size) if size else None,
            "dtype": str(dtype).replace("torch.", ""), "command": "python -m eval synth",
            # (what rendered the folder: in meta.json and in --json alike)
            "environment": environment("synth", args, seed=args.seed)}
    try:
        summary = write_synthetic_sequence(args.out, rendered(), meta=meta, progress=not args.no_progress,
                                           total=args.pairs)
    except _Unstorable as err:
        print(f"error: {err}", file=sys.stderr)
        return 2

    if args.json is not None:
        write_json(make_parent(args.json), {**summary, **meta, "pairs": rows})
    # (printed after the files are written: a reader of stdout that goes away (| head) loses none)
    height, width = summary["size"]
    print(f"wrote {summary['num_pairs']} pairs of preset {args.preset!r} (seed {args.seed}, {height}x{width}) "
          f"to {summary['root']} ({summary['bytes'] / 1e6:.2f} MB)")
    print(f"{'pair':>6} {'x_d m':>8} {'z_d m':>8} {'yaw deg':>8} {'valid %':>8} {'road %':>8} {'max |F| px':>10}")
    for r in rows:
        print(f"{r['index']:>6d} {r['x_d']:>8.4f} {r['z_d']:>8.4f} {r['yaw_deg']:>8.4f} {r['valid_pct']:>8.2f} "
              f"{_fmt(r['road_pct']):>8} {r['max_flow_px']:>10.2f}")
    print("files: " + ", ".join(f"{k}/ {v}" for k, v in summary["files"].items()) + ", poses.txt, meta.json")
    return 0
