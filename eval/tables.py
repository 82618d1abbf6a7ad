"""``python -m eval tables``: the paper's fitting tables, reproduced.

Each scenario fits the freespace model to the ground-truth flow inside the road mask and reports
the metrics (paper eq. 25-28, :func:`fsof_torch.evaluation.metrics.flow_metrics`) of the fitted model flow
against that ground truth, aggregated over all road pixels of the scenario's pairs, with the
paper's published figures beside ours:

* CVC12-like (displacement model, :func:`fsof_torch.estimation.flow_fit.fit_displacement`): presets
  ``cvc-simple`` / ``cvc-complex`` × vehicle speed ×1 / ×4; e_A (rad), e_E (px).
* CARLA-like (velocity model, :func:`fsof_torch.estimation.flow_fit.fit_velocity`): ``carla-straight`` /
  ``carla-turning`` × camera roll 0, ±5°, ±10°; e_A, e_E on px/s flow, and the fitted roll.
* Real KITTI (``../shared/data/kitti15_000000``): sparse ground truth inside the hand-drawn
  ``road.json``, the paper's model and the model with pitch; e_A, e_E, e_U, e_V.

The synthetic scenes are this project's renders (:mod:`fsof_torch.data.scene`), not the paper's data,
and the KITTI row is one frame, not the paper's frames: compare orders of magnitude.

Example::

    python -m eval tables --out runs/tables --size 188 621 --pairs 2
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

from .paths import MAX_SIDE, file_path, given_path

#: The paper's published figures (freespace-optical-flow.tex, Tables "CVC12", "CARLA", "KITTI").
PAPER_CVC12 = {("simple", 1): (0.003, 0.609), ("simple", 4): (0.003, 0.704),
               ("complex", 1): (0.089, 0.534), ("complex", 4): (0.030, 0.244)}
PAPER_CARLA = {("straight", 0): (0.039, 0.526), ("straight", 5): (0.038, 0.516),
               ("straight", -5): (0.040, 0.566), ("straight", 10): (0.034, 0.521),
               ("straight", -10): (0.041, 0.627), ("turning", 0): (0.034, 1.260),
               ("turning", 5): (0.032, 1.285), ("turning", -5): (0.035, 1.275),
               ("turning", 10): (0.033, 1.357), ("turning", -10): (0.037, 1.325)}
PAPER_KITTI = {"straight": (0.036, 0.921, 0.255, 0.465), "turning": (0.050, 1.005, 0.599, 0.814)}

DEFAULT_KITTI = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti15_000000"
METRICS = ("e_A", "e_E", "e_U", "e_V", "Fl")
#: the files of the KITTI sample that the KITTI table reads (:func:`load_kitti`)
KITTI_FILES = ("flow_noc_10.png", "road.json", "calib_cam_to_cam.txt")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=given_path, default=Path("runs/tables"), metavar="DIR",
                        help="output folder for tables.json and tables.md (default runs/tables)")
    parser.add_argument("--json", type=file_path, default=None, metavar="PATH",
                        help="write the JSON here instead of DIR/tables.json")
    # (the synthetic tables' options default to None: not given, so that one given to a run of
    # the KITTI table alone is refused, even at its default)
    parser.add_argument("--size", type=int, nargs=2, default=None, metavar=("H", "W"),
                        help=f"render size of the synthetic scenes, each side 16 to {MAX_SIDE} "
                             "(default 375 1242; --quick: 96 320)")
    parser.add_argument("--pairs", type=int, default=None, metavar="N",
                        help="frame pairs per synthetic scenario (default 3; --quick: 1)")
    parser.add_argument("--seed", type=int, default=None, help="scene seed of the synthetic scenes (default 0)")
    # (None: not given; the shared sample then, skipped with a note where it is absent)
    parser.add_argument("--kitti", type=given_path, default=None, metavar="DIR",
                        help=f"KITTI flow sample folder (default {DEFAULT_KITTI})")
    parser.add_argument("--no-kitti", action="store_true", help="skip the real-KITTI table")
    parser.add_argument("--only", choices=("cvc12", "carla", "kitti"), action="append", default=None,
                        help="run only these tables (repeatable)")
    parser.add_argument("--quick", action="store_true",
                        help="small and fast synthetic tables: 96x320, one pair, rolls 0 and ±5° (a --size "
                             "or --pairs given replaces its size or pairs)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


# -- helpers shared by the analysis subcommands ---------------------------------------------------

def _cell(row: dict, column: tuple) -> str:
    """A row's value in ``column`` (key, header, format[, factor]): formatted, times the factor
    where one is given (a fraction printed in percent), or '-' where it is None or NaN."""
    key, _, fmt, *factor = column
    value = row.get(key)
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return format(value * factor[0] if factor else value, fmt)


def format_table(rows: list[dict], columns: list[tuple]) -> str:
    """A plain-text table: ``columns`` are (key, header, format) with format like ``.3f`` or ``s``,
    or (key, header, format, factor) for a value printed times ``factor`` (100: percent)."""
    cells = [[c[1] for c in columns]]
    for r in rows:
        cells.append([_cell(r, c) for c in columns])
    widths = [max(len(c[i]) for c in cells) for i in range(len(columns))]
    out = ["  ".join(c.rjust(w) for c, w in zip(cells[0], widths)),
           "  ".join("-" * w for w in widths)]
    out += ["  ".join(c.rjust(w) for c, w in zip(line, widths)) for line in cells[1:]]
    return "\n".join(out)


def markdown_table(rows: list[dict], columns: list[tuple]) -> str:
    """The same table as Markdown."""
    head = "| " + " | ".join(c[1] for c in columns) + " |"
    sep = "| " + " | ".join("---" for _ in columns) + " |"
    body = ["| " + " | ".join(_cell(r, c) for c in columns) + " |" for r in rows]
    return "\n".join([head, sep, *body])


def _merge(acc: dict | None, m: dict) -> dict:
    """Pixel-weighted accumulation of flow_metrics dicts (KITTI style: over all pixels)."""
    if acc is None:
        acc = {k: 0.0 for k in METRICS} | {"n_pixels": 0}
    n = int(m["n_pixels"])
    for k in METRICS:
        acc[k] += float(m[k]) * n
    acc["n_pixels"] += n
    return acc


def _finish(acc: dict, what: str) -> dict:
    """Pixel-weighted means; over no pixel the metrics are None (printed '-', JSON null), with a
    warning, rather than zeros that read as a perfect fit."""
    n = acc["n_pixels"]
    return {k: acc[k] / n for k in METRICS} | {"n_pixels": n} if n else _no_pixels(what)


def _no_pixels(what: str) -> dict:
    from fsof_torch.io.progress import print_above_bars

    print_above_bars(f"warning: {what}: no road pixel with valid ground truth and model flow; its metrics are '-'")
    return {k: None for k in METRICS} | {"n_pixels": 0}


# -- the three tables -------------------------------------------------------------------------------

def cvc12_table(size, pairs: int, seed: int, bar=None) -> list[dict]:
    from fsof_torch.estimation.flow_fit import fit_displacement
    from fsof_torch.evaluation.metrics import flow_metrics
    from fsof_torch.data.scene import render_pair

    rows = []
    for scenario in ("simple", "complex"):
        for speed in (1, 4):
            acc, z_err, ok = None, [], 0
            for index in range(pairs):
                pair = render_pair(f"cvc-{scenario}", index, seed=seed, size=size, dtype=torch.float64,
                                   speed_factor=float(speed))
                flow, valid, road = pair["flow"][None], pair["valid"][None], pair["road"][None]
                camera = pair["camera"]
                fit = fit_displacement(flow, road & valid, camera.replace(roll=0.0, pitch=0.0), fit_roll=True)
                acc = _merge(acc, flow_metrics(fit.flow, flow, mask=road, valid=valid & fit.valid))
                z_err.append(abs(float(fit.z_d[0]) - pair["odometry"]["z_d"]))
                ok += int(fit.success.all())
                if bar is not None:
                    bar.update(1)
            paper = PAPER_CVC12[(scenario, speed)]
            rows.append({"scenario": scenario, "speed": f"x{speed}", **_finish(acc, f"CVC12-like {scenario} x{speed}"),
                         "z_d_abs_error_m": sum(z_err) / len(z_err), "fits_ok": f"{ok}/{pairs}",
                         "paper_e_A": paper[0], "paper_e_E": paper[1]})
    return rows


def carla_table(size, pairs: int, seed: int, rolls, bar=None) -> list[dict]:
    from fsof_torch.estimation.flow_fit import fit_velocity
    from fsof_torch.evaluation.metrics import flow_metrics
    from fsof_torch.data.scene import render_pair

    rows = []
    for direction in ("straight", "turning"):
        for roll_deg in rolls:
            acc, roll_err, ok = None, [], 0
            for index in range(pairs):
                pair = render_pair(f"carla-{direction}", index, seed=seed, size=size, dtype=torch.float64,
                                   roll=math.radians(roll_deg))
                flow, valid, road = pair["flow_velocity"][None], pair["valid"][None], pair["road"][None]
                camera = pair["camera"]
                # The mounting roll is unknown to the fit: it starts from 0 and estimates it.
                fit = fit_velocity(flow, road & valid, camera.replace(roll=0.0), pair["velocity"]["wheelbase"],
                                   fit_roll=True)
                acc = _merge(acc, flow_metrics(fit.flow, flow, mask=road, valid=valid & fit.valid))
                roll_err.append(abs(math.degrees(float(fit.roll[0])) - roll_deg))
                ok += int(fit.success.all())
                if bar is not None:
                    bar.update(1)
            paper = PAPER_CARLA[(direction, roll_deg)]
            rows.append({"direction": direction, "roll_deg": roll_deg,
                         **_finish(acc, f"CARLA-like {direction} roll {roll_deg}"),
                         "roll_abs_error_deg": sum(roll_err) / len(roll_err), "fits_ok": f"{ok}/{pairs}",
                         "paper_e_A": paper[0], "paper_e_E": paper[1]})
    return rows


def load_kitti(folder: Path) -> dict:
    """The KITTI sample of the KITTI table: ``flow``, ``valid``, ``road`` (1, 1, H, W) and ``camera``
    from ``flow_noc_10.png``, ``road.json`` and ``calib_cam_to_cam.txt``. Raises ValueError (or
    FileNotFoundError) naming the file, ValueError when the flow's size is not the one the
    calibration states for camera 2 (``S_rect_02``, where it has that row: a cropped or resized
    flow was fitted with another image's principal point), when ``road.json`` states another size than
    the flow's (a polygon drawn for another image), and when the road holds no valid pixel."""
    from fsof_torch.data.folders import calibration_size
    from fsof_torch.geometry.camera import Camera
    from fsof_torch.io import read_kitti_flow, read_road_mask

    flow, valid = read_kitti_flow(folder / "flow_noc_10.png")
    H, W = flow.shape[-2:]
    camera = Camera.from_kitti(folder / "calib_cam_to_cam.txt", cam=2, height=1.65)
    calibrated = calibration_size(folder / "calib_cam_to_cam.txt", 2)  # (the file read: it is one)
    if calibrated is not None and calibrated != (H, W):
        raise ValueError(f"{str(folder / 'flow_noc_10.png')!r} is {H}x{W}, but "
                         f"{str(folder / 'calib_cam_to_cam.txt')!r} is for {calibrated[0]}x{calibrated[1]} images "
                         f"(S_rect_02); expected a flow of the calibrated size")
    try:  # (a polygon drawn for another image size is the library's ValueError, not stretched)
        road = read_road_mask(folder / "road.json", size=(H, W))
    except TypeError as err:  # a malformed polygon
        raise ValueError(str(err)) from None
    if not bool((road & valid).any()):
        raise ValueError(f"{str(folder / 'road.json')!r} covers no pixel with valid ground truth in "
                         f"{str(folder / 'flow_noc_10.png')!r}")
    return {"flow": flow[None].double(), "valid": valid[None], "road": road[None], "camera": camera}


def kitti_table(sample: dict, bar=None) -> list[dict]:
    """The KITTI table's rows for the sample of :func:`load_kitti`."""
    from fsof_torch.estimation.flow_fit import fit_displacement
    from fsof_torch.evaluation.metrics import flow_metrics

    flow, valid, road, camera = sample["flow"], sample["valid"], sample["road"], sample["camera"]
    rows = []
    for name, fit_pitch in (("paper model", False), ("with pitch", True)):
        fit = fit_displacement(flow, road & valid, camera, fit_roll=True, fit_pitch=fit_pitch)
        m = flow_metrics(fit.flow, flow, mask=road, valid=valid & fit.valid)
        n = int(m["n_pixels"])
        metrics = {k: float(m[k]) for k in METRICS} | {"n_pixels": n} if n else _no_pixels(f"KITTI {name}")
        rows.append({"model": name, **metrics,
                     "x_d": float(fit.x_d[0]), "z_d": float(fit.z_d[0]), "yaw_deg": math.degrees(float(fit.yaw[0])),
                     "roll_deg": math.degrees(float(fit.roll[0])), "pitch_deg": math.degrees(float(fit.pitch[0])),
                     "success": bool(fit.success.all()),
                     "paper_straight": list(PAPER_KITTI["straight"]), "paper_turning": list(PAPER_KITTI["turning"])})
        if bar is not None:
            bar.update(1)
    return rows


# The renders are exact planes, so the synthetic errors are at rounding level: scientific notation.
CVC_COLUMNS = [("scenario", "scenario", "s"), ("speed", "speed", "s"), ("e_A", "e_A rad", ".2e"),
               ("paper_e_A", "paper e_A", ".3f"), ("e_E", "e_E px", ".2e"), ("paper_e_E", "paper e_E", ".3f"),
               ("e_U", "e_U px", ".2e"), ("e_V", "e_V px", ".2e"), ("z_d_abs_error_m", "z_d abs err m", ".2e"),
               ("n_pixels", "pixels", "d"), ("fits_ok", "fits ok", "s")]
CARLA_COLUMNS = [("direction", "direction", "s"), ("roll_deg", "roll deg", "d"), ("e_A", "e_A rad", ".2e"),
                 ("paper_e_A", "paper e_A", ".3f"), ("e_E", "e_E px/s", ".2e"), ("paper_e_E", "paper e_E", ".3f"),
                 ("roll_abs_error_deg", "roll abs err deg", ".2e"), ("n_pixels", "pixels", "d"),
                 ("fits_ok", "fits ok", "s")]
KITTI_COLUMNS = [("model", "model", "s"), ("e_A", "e_A rad", ".4f"), ("e_E", "e_E px", ".4f"),
                 ("e_U", "e_U px", ".4f"), ("e_V", "e_V px", ".4f"),
                 # (KITTI's Fl-all in percent, as KITTI and the train job print it; a fraction in the JSON)
                 ("Fl", "Fl %", ".3f", 100),
                 ("roll_deg", "roll deg", ".3f"), ("pitch_deg", "pitch deg", ".3f"), ("z_d", "z_d m", ".3f"),
                 ("n_pixels", "pixels", "d")]
KITTI_PAPER_NOTE = ("paper (its KITTI frames): straight e_A 0.036, e_E 0.921, e_U 0.255, e_V 0.465; "
                    "turning e_A 0.050, e_E 1.005, e_U 0.599, e_V 0.814")


def _unused_option(args: argparse.Namespace) -> str | None:
    """An option given that this run does not use, or one that leaves no table to make, as a
    message naming it, or None: refused rather than silently ignored."""
    if args.no_kitti and args.only:
        return (f"--no-kitti: not with --only, which names the tables to make "
                f"(--only {' --only '.join(args.only)})")
    if args.kitti is not None and args.no_kitti:
        return "--kitti: applies to the KITTI table, which --no-kitti skips"
    if args.kitti is not None and args.only and "kitti" not in args.only:
        return (f"--kitti: applies to the KITTI table, which this run does not make "
                f"(--only {' --only '.join(args.only)})")
    if args.only and not {"cvc12", "carla"} & set(args.only):
        given = {"--size": args.size is not None, "--pairs": args.pairs is not None, "--seed": args.seed is not None,
                 "--quick": args.quick}
        for option, is_given in given.items():
            if is_given:
                return (f"{option}: applies to the synthetic tables (cvc12, carla), which this run does not "
                        f"make (--only {' --only '.join(args.only)})")
    return None


def run(args: argparse.Namespace) -> int:
    from fsof_torch.io import write_json, write_text

    from .paths import (bad_file, bad_folder, bad_json_target, bad_lookup, bad_size, first_bad, make_parent,
                        remove_outputs)
    from fsof_torch.io.progress import progress_bar

    from .provenance import environment

    bad = _unused_option(args)
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    size = tuple(args.size) if args.size is not None else ((96, 320) if args.quick else (375, 1242))
    pairs = args.pairs if args.pairs is not None else (1 if args.quick else 3)
    seed = 0 if args.seed is None else args.seed
    if min(size) < 16:
        print(f"error: --size: expected H, W >= 16, got {list(size)}", file=sys.stderr)
        return 2
    bad = bad_size(size, "--size")
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    from fsof_torch.data.scene.render import MAX_FRAME

    if not 1 <= pairs <= MAX_FRAME:  # (pairs 0 .. N - 1: the scenes' frames end at MAX_FRAME)
        print(f"error: --pairs: expected 1 to {MAX_FRAME}, got {pairs}", file=sys.stderr)
        return 2
    tables = set(args.only or ("cvc12", "carla", "kitti"))
    if args.no_kitti:
        tables.discard("kitti")
    kitti_folder = DEFAULT_KITTI if args.kitti is None else args.kitti
    bad = bad_lookup(args.kitti, "--kitti") if "kitti" in tables else None
    if bad is None and "kitti" in tables:  # (a FIFO: "no KITTI sample at", "no calibration file at")
        from refine.inputs import special_input

        bad = first_bad(*(special_input(p, "--kitti") for p in (kitti_folder, *(kitti_folder / n for n in KITTI_FILES))))
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    if "kitti" in tables and not (kitti_folder / "flow_noc_10.png").is_file():
        if args.kitti is not None or "kitti" in (args.only or ()):
            # asked for: an error, not an empty table
            option = "--kitti" if args.kitti is not None else "--only kitti"
            print(f"error: {option}: no KITTI sample (flow_noc_10.png) at {str(kitti_folder)!r}", file=sys.stderr)
            return 2
        print(f"note: no KITTI sample at {kitti_folder}; skipping the KITTI table", file=sys.stderr)
        tables.discard("kitti")
    # the sample's files that the KITTI table reads, and its folder: --json may name none of them
    # nor the folder's other files (the sample's images)
    inputs = {f"--kitti ({name})": kitti_folder / name for name in KITTI_FILES} if "kitti" in tables else {}
    if "kitti" in tables:
        inputs["--kitti"] = kitti_folder
    bad = first_bad(bad_folder(args.out, "--out", ["tables.md"] + ([] if args.json else ["tables.json"])),
                    bad_file(args.json, "--json", args.out), bad_json_target(args.json, [args.out / "tables.md"], inputs))
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    kitti = None
    if "kitti" in tables:  # all of the sample's files, before the synthetic tables
        try:
            kitti = load_kitti(kitti_folder)
        except (ValueError, FileNotFoundError, IsADirectoryError) as err:  # (a folder: was a traceback)
            print(f"error: --kitti: {str(err).removeprefix('path: ')}", file=sys.stderr)
            return 2
    # the inputs are good: an earlier run's files go (DIR/tables.json where this run writes its
    # JSON elsewhere), not to be read as this run's
    remove_outputs(args.out, ["tables.json", "tables.md"])
    if args.json is not None:  # (and its JSON elsewhere: a run that stops would leave it as its own)
        remove_outputs(args.json.parent, [args.json.name])
    rolls = (0, 5, -5) if args.quick else (0, 5, -5, 10, -10)
    total = (4 * pairs if "cvc12" in tables else 0) + (2 * len(rolls) * pairs if "carla" in tables else 0) \
        + (2 if "kitti" in tables else 0)

    settings = {"size": list(size), "pairs": pairs, "seed": seed, "quick": bool(args.quick), "rolls_deg": list(rolls)}
    result: dict = {"settings": {**(settings if tables & {"cvc12", "carla"} else {}),
                                 "kitti": str(kitti_folder) if "kitti" in tables else None}}
    md = ["# Freespace model fitted to ground-truth flow (python -m eval tables)", ""]
    with progress_bar(total=total, enabled=not args.no_progress, desc="tables", unit="fit") as bar:
        if "cvc12" in tables:
            result["cvc12"] = cvc12_table(size, pairs, seed, bar)
        if "carla" in tables:
            result["carla"] = carla_table(size, pairs, seed, rolls, bar)
        if "kitti" in tables:
            result["kitti"] = kitti_table(kitti, bar)

    sections = [("cvc12", "CVC12-like (displacement model, e_A rad, e_E px)", CVC_COLUMNS),
                ("carla", "CARLA-like (velocity model, flow in px/s)", CARLA_COLUMNS),
                ("kitti", f"Real KITTI ({kitti_folder.name}, GT inside road.json)", KITTI_COLUMNS)]
    shown = [(key, title, columns) for key, title, columns in sections if key in result]
    for key, title, columns in shown:
        md += [f"## {title}", "", markdown_table(result[key], columns), ""]
        if key == "kitti":
            md += [KITTI_PAPER_NOTE, ""]
    args.out.mkdir(parents=True, exist_ok=True)
    json_path = args.json if args.json is not None else args.out / "tables.json"
    # (the seed where a synthetic table drew scenes with it)
    result["environment"] = environment("tables", args, seed=seed if {"cvc12", "carla"} & set(result) else None)
    write_json(make_parent(json_path), result)
    write_text(args.out / "tables.md", "\n".join(md))
    # (printed after the files are written: a reader of stdout that goes away (| head) loses none)
    for key, title, columns in shown:
        print(f"\n{title}\n" + format_table(result[key], columns))
        if key == "kitti":
            print(KITTI_PAPER_NOTE)
    print(f"\nwrote {json_path} and {args.out / 'tables.md'}")
    return 0
