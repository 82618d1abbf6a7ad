"""``python -m eval vflow``: the V-flow map of a flow field, its fitted eq. 24 curve and the fitted
F_v map (the paper's Fig. "optical flow modeling in the special case"), and, for a rendered
preset, the freespace detected from the flow.

Input: a synthetic preset (its ground-truth flow, road mask and camera) or a flow file
(``.png`` KITTI, ``.flo``, ``.npy``) with an optional road mask file.

Writes ``vflow_map.png`` (the row histogram of F_v with the per-row dominant values and the fitted
curve), ``fv_observed.png``, ``fv_fitted.png``, ``fv_error.png`` (|observed - fitted| in the mask),
``freespace.png`` (preset with the displacement model only) and ``vflow.json`` into ``--out``,
from which the files of an earlier run are removed first, once the inputs are checked.

Example::

    python -m eval vflow --preset cvc-complex --out runs/vflow
    python -m eval vflow --flow ../shared/data/kitti15_000000/flow_noc_10.png \\
        --mask ../shared/data/kitti15_000000/road.json --out runs/vflow_kitti
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

from fsof_torch.io.atomic import atomic_path

from .paths import MAX_SIDE, file_path, given_path

# The largest --index: 10 000 pairs are over 15 minutes of driving at 10 Hz, and the scene is laid
# out up to the pair asked for, so time and memory grow with the index.
MAX_INDEX = 10_000
# The largest --bins: finer than any flow's range needs; the map holds H × bins counts, and far
# more bins only fill memory.
MAX_BINS = 65_536
#: the fewest mask pixels of a row that the curve fit uses (fit_vflow_curve's min_row_pixels, its
#: default): a row with fewer has a support above 0 but is neither used nor an outlier
MIN_ROW_PIXELS = 3
#: the resolution of the figures
DPI = 110


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group()
    src.add_argument("--preset", default=None, help="render this scene preset (default cvc-complex)")
    src.add_argument("--flow", type=given_path, default=None, metavar="FILE", help="a flow file (.png KITTI, .flo, .npy)")
    parser.add_argument("--mask", type=given_path, default=None, metavar="FILE",
                        help="road mask for --flow (PNG or polygon JSON); default: the flow's valid pixels")
    # (None: not given, so that a preset-only option given with --flow is refused, even at its default)
    parser.add_argument("--index", type=int, default=None,
                        help=f"pair index of the preset, 0 to {MAX_INDEX} (default 0)")
    parser.add_argument("--seed", type=int, default=None, help="scene seed of the preset (default 0)")
    parser.add_argument("--size", type=int, nargs=2, default=None, metavar=("H", "W"),
                        help=f"render size of the preset, each side 16 to {MAX_SIDE} (default: the preset's)")
    parser.add_argument("--model", choices=("displacement", "velocity"), default="displacement",
                        help="curve of eq. 24 to fit; velocity uses the preset's px/s flow (default displacement)")
    parser.add_argument("--road-only", action="store_true",
                        help="preset: build the map from the road pixels only (default: all valid pixels, "
                             "so obstacles show in the map and the fit must be robust to them)")
    parser.add_argument("--bins", type=int, default=256, help=f"histogram bins, 2 to {MAX_BINS} (default 256)")
    parser.add_argument("--statistic", choices=("peak", "median"), default="peak",
                        help="per-row dominant flow (default peak)")
    parser.add_argument("--inlier-threshold", type=float, default=0.5, metavar="PX",
                        help="row residual below which a row is an inlier of the curve (default 0.5)")
    parser.add_argument("--relative-threshold", type=float, default=0.05, metavar="FRAC",
                        help="relative row threshold: max(PX, FRAC·|F_v|) (default 0.05)")
    parser.add_argument("--out", type=given_path, default=Path("runs/vflow"), metavar="DIR",
                        help="output folder (default runs/vflow)")
    parser.add_argument("--json", type=file_path, default=None, metavar="PATH",
                        help="write the JSON here instead of DIR/vflow.json")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _plot_map(hist: torch.Tensor, edges: torch.Tensor, curve, path: Path, unit: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    H = hist.shape[0]
    a_unit = "1/px" if unit == "px" else "1/(px s)"
    fig, ax = plt.subplots(figsize=(6, 5), dpi=DPI)
    lo, hi = float(edges[0]), float(edges[-1])
    shown = ax.imshow(torch.log1p(hist).numpy(), aspect="auto", cmap="magma", origin="upper",
                      extent=(lo, hi, H - 0.5, -0.5), interpolation="nearest")
    fig.colorbar(shown, ax=ax, label="log(1 + pixels in the row's bin)")
    rows = curve.row_support[0] >= MIN_ROW_PIXELS  # (the rows the fit used)
    v = torch.arange(H, dtype=torch.float64)
    inl = curve.row_inliers[0]
    # a failed fit has no curve (a = v0 = 0, nothing drawn); its rows are those of the curve it
    # rejected, not the inliers of an "eq. 24 fit: a=0.000e+00" that the legend named
    ok = bool(curve.success[0])
    ax.scatter(curve.row_value[0][rows & ~inl].double().numpy(), v[rows & ~inl].numpy(), s=6, c="cyan",
               label="dominant F_v, " + ("outlier rows" if ok else "other rows"))
    ax.scatter(curve.row_value[0][inl].double().numpy(), v[inl].numpy(), s=6, c="lime",
               label="dominant F_v, " + ("inlier rows" if ok else "rows near the rejected curve"))
    fitted = curve.fitted[0, 0, :, 0].double()
    defined = curve.fitted_valid[0, 0, :, 0]
    ax.plot(fitted[defined].numpy(), v[defined].numpy(), color="white", linewidth=1.5,
            label=f"eq. 24 fit: a={float(curve.a[0]):.3e} {a_unit}, v0={float(curve.v0[0]):.2f} px" if ok else
            f"eq. 24 fit failed ({float(curve.nfa[0]):.2g} false alarms): no curve")
    ax.set_xlim(lo, hi)
    ax.set_xlabel(f"vertical flow F_v ({unit})")
    ax.set_ylabel("image row v (px)")
    ax.set_title("V-flow map (log count per row and bin)")
    # (where the legend hides the fewest points: the curve runs into the lower right corner of a
    # forward motion's map, the lower left of a reversing one's)
    ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    _reduce_map(shown, hist, lo, hi)
    with atomic_path(path) as tmp:  # (never half a figure)
        fig.savefig(tmp, dpi=DPI)
    plt.close(fig)


def _reduce_map(shown, hist: torch.Tensor, lo: float, hi: float) -> None:
    """A V-flow map of more rows or bins than its panel has pixels drawn reduced, each drawn pixel
    the largest count of the rows and bins it covers, placed over them: shrunk by matplotlib's
    nearest-neighbour drawing, it dropped whole rows and bins (of a map of one count per row, 12
    of 100 rows' counts were drawn at 4096 bins, 153 of 375 at 1024, 410 of 1200 at 256)."""
    import torch.nn.functional as F

    from fsof_torch.evaluation.figures import drawing_factor

    (H, bins), box = hist.shape, shown.axes.get_window_extent()
    fr, fc = drawing_factor((H, 1), (box.height, 1.0)), drawing_factor((1, bins), (1.0, box.width))
    if fr == fc == 1:
        return
    most = F.max_pool2d(hist[None, None].double(), (fr, fc), ceil_mode=True)[0, 0]
    shown.set_data(torch.log1p(most).numpy())
    # (the last block, cut by the map's edge, reaches beyond the axes, which stay the map's)
    shown.set_extent((lo, lo + most.shape[1] * fc * (hi - lo) / bins, most.shape[0] * fr - 0.5, -0.5))
    shown.axes.set_xlim(lo, hi)
    shown.axes.set_ylim(H - 0.5, -0.5)
    shown.colorbar.set_label("log(1 + pixels in the row's bin),\nthe most of those a drawn pixel covers")


def _colour_range(values: torch.Tensor) -> tuple[float, float]:
    """The colour range of an F_v map on a diverging colour map: ±max |F_v|, so that every value
    is shown and its sign reads at a glance (F_v < 0 above the horizon, > 0 below, 0 on it)."""
    bound = max(float(values.abs().max()), 1e-6)
    return -bound, bound


def error_vmax(errors: torch.Tensor) -> float:
    """The top of the error map's colour bar: the larger of 1 and the 95th percentile of
    ``errors`` (1 where there is none). NumPy's percentile (linear, as torch's): ``torch.quantile``
    refuses more than 2**24 values, a flow of 17 megapixels below the horizon (a traceback after
    every other figure was drawn, and no vflow.json)."""
    import numpy as np

    if errors.numel() == 0:
        return 1.0
    return max(1.0, float(np.quantile(errors.detach().cpu().double().numpy(), 0.95)))


def _extend(values: torch.Tensor, vmin: float, vmax: float) -> str:
    """The colour bar's ``extend``: an arrow at each end where ``values`` are clipped."""
    below, above = bool((values < vmin).any()), bool((values > vmax).any())
    return {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[(below, above)]


def _plot_image(img: torch.Tensor, valid: torch.Tensor, path: Path, title: str, cmap: str,
                vmin: float, vmax: float, label: str) -> None:
    """``img`` where ``valid``, coloured on [vmin, vmax]; the colour bar (labelled ``label``, with
    its unit) has an arrow at each end where the shown values are clipped. Pixels without a value
    are mid grey (``NO_VALUE_RGB``, named under the bar): left transparent, they were the figure's
    white, the diverging F_v map's colour of 0."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from fsof_torch.evaluation.figures import drawing_factor, place_reduced, reduce_values
    from fsof_torch.evaluation.visualize import NO_VALUE_RGB

    data = np.ma.masked_array(img.double().numpy(), mask=~valid.numpy())
    H, W = img.shape
    fig, ax = plt.subplots(figsize=(min(12.0, 2 + 8 * W / max(H, W)), min(8.0, 1.5 + 8 * H / max(H, W))), dpi=DPI)
    colours = matplotlib.colormaps[cmap].with_extremes(bad=tuple(c / 255.0 for c in NO_VALUE_RGB))
    im = ax.imshow(data, cmap=colours, vmin=vmin, vmax=vmax, interpolation="nearest",
                   extent=(-0.5, W - 0.5, H - 0.5, -0.5))
    fig.colorbar(im, ax=ax, fraction=0.03, label=f"{label}\ngrey: no value", extend=_extend(img[valid], vmin, vmax))
    ax.set_title(title)
    ax.set_axis_off()
    fig.tight_layout()
    # A picture larger than its panel is shrunk by dropping whole rows and columns (a KITTI frame:
    # 22 of 31 sparse ground-truth lines were drawn): drawn reduced instead, each drawn pixel the
    # mean of the pixels with a value it covers, and placed over them.
    box = ax.get_window_extent()
    factor = drawing_factor((H, W), (box.height, box.width))
    if factor > 1:
        mean, has = reduce_values(img[None], valid[None], valid[None] & ~torch.isfinite(img[None]), factor)
        im.set_data(np.ma.masked_array(mean[0].numpy(), mask=~has[0].numpy()))
        place_reduced(im, (H, W), factor)
    with atomic_path(path) as tmp:  # (never half a figure)
        fig.savefig(tmp, dpi=DPI)
    plt.close(fig)


def _plot_freespace(image: torch.Tensor, free: torch.Tensor, road: torch.Tensor, path: Path, iou: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.patches import Patch

    from fsof_torch.evaluation.figures import drawing_factor, place_reduced, reduce_values

    # freespace on the road, road missed, freespace off the road (each its own colour: a
    # freespace that spills onto a pavement must not read as road found)
    classes = [(free[0] & road[0], (0.0, 1.0, 0.0), "freespace on the road"),
               (road[0] & ~free[0], (1.0, 0.0, 0.0), "road missed"),
               (free[0] & ~road[0], (1.0, 0.0, 1.0), "freespace off the road")]
    H, W = free.shape[-2:]
    fig, ax = plt.subplots(figsize=(10, 10 * H / W + 0.6), dpi=DPI)
    shown = ax.imshow(torch.zeros(H, W, 3).numpy(), interpolation="nearest")
    ax.set_title(f"freespace detected from the flow, IoU with the road {iou:.3f}")
    ax.legend(handles=[Patch(facecolor=colour, alpha=0.5, label=f"{label} ({int(where.sum())} px)")
                       for where, colour, label in classes], loc="upper right", fontsize=8)
    ax.set_axis_off()
    fig.tight_layout()
    # A picture larger than its panel was shrunk by dropping whole rows and columns (of strips of
    # freespace off the road one pixel wide in a 375 x 1242 frame, 92 of 138 were drawn): drawn
    # reduced instead, the image the mean of the pixels it covers, tinted by the class of any of
    # them, a miss over a find (a later class over an earlier one), placed over them.
    box = ax.get_window_extent()
    factor = drawing_factor((H, W), (box.height, box.width))
    every, none = torch.ones(1, H, W, dtype=torch.bool), torch.zeros(1, H, W, dtype=torch.bool)
    rgb = reduce_values((image / 255.0).clamp(0, 1), every, none, factor)[0].permute(1, 2, 0)
    overlay = rgb
    for where, colour, _ in classes:
        any_of = reduce_values(where[None], every, none, factor)[0][0] > 0
        overlay = torch.where(any_of.unsqueeze(-1), 0.5 * rgb + 0.5 * torch.tensor(colour, dtype=torch.float64), overlay)
    shown.set_data(overlay.numpy())
    place_reduced(shown, (H, W), factor)
    with atomic_path(path) as tmp:  # (never half a figure)
        fig.savefig(tmp, dpi=DPI)
    plt.close(fig)


def _unused_option(args: argparse.Namespace) -> str | None:
    """An option given that the chosen input does not use, as a message naming it, or None: it is
    refused rather than silently ignored (``--preset`` with ``--flow``: argparse refuses it)."""
    if args.flow is not None:
        given = {"--road-only": args.road_only, "--index": args.index is not None, "--seed": args.seed is not None,
                 "--size": args.size is not None}
        for option, is_given in given.items():
            if is_given:
                return f"{option}: applies to a rendered --preset, not to --flow"
    elif args.mask is not None:
        return "--mask: applies to --flow; a rendered preset has its own road mask (--road-only uses it)"
    return None


def run(args: argparse.Namespace) -> int:
    from fsof_torch.io import write_json
    from fsof_torch import detect_freespace, fit_vflow_curve, vflow_map

    from refine.inputs import special_input

    from .paths import (bad_file, bad_folder, bad_json_target, bad_lookup, bad_out_inputs, bad_size, first_bad,
                        make_parent, remove_outputs)
    from .provenance import environment
    from fsof_torch.io.progress import progress_bar

    if not 2 <= args.bins <= MAX_BINS:
        print(f"error: --bins: expected 2 to {MAX_BINS}, got {args.bins}", file=sys.stderr)
        return 2
    for option, value in (("--inlier-threshold", args.inlier_threshold),
                          ("--relative-threshold", args.relative_threshold)):
        if not (math.isfinite(value) and value >= 0):
            print(f"error: {option}: expected a finite number >= 0, got {value}", file=sys.stderr)
            return 2
    if args.size is not None and min(args.size) < 16:
        print(f"error: --size: expected H, W >= 16, got {args.size}", file=sys.stderr)
        return 2
    bad = bad_size(args.size, "--size")
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    bad = _unused_option(args)
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    index = 0 if args.index is None else args.index
    seed = 0 if args.seed is None else args.seed
    if not 0 <= index <= MAX_INDEX:
        print(f"error: --index: expected a pair index in [0, {MAX_INDEX}], got {index}", file=sys.stderr)
        return 2
    steps = ["load", "V-flow map", "curve fit", "plots"]
    preset = args.preset if args.flow is None else None
    if args.flow is None and preset is None:
        preset = "cvc-complex"
    if preset is not None and args.model == "displacement":
        steps.insert(3, "freespace")
    figures = ["vflow_map.png", "fv_observed.png", "fv_fitted.png", "fv_error.png", "freespace.png"]
    written = [args.out / f for f in figures if f != "freespace.png" or "freespace" in steps]
    bad = first_bad(bad_lookup(args.flow, "--flow"), bad_lookup(args.mask, "--mask"),
                    special_input(args.flow, "--flow"), special_input(args.mask, "--mask"),
                    bad_folder(args.out, "--out", figures + ([] if args.json else ["vflow.json"])),
                    bad_out_inputs(args.out, figures + ["vflow.json"], {"--flow": args.flow, "--mask": args.mask}),
                    bad_file(args.json, "--json", args.out),
                    bad_json_target(args.json, written, {"--flow": args.flow, "--mask": args.mask}))
    if bad is not None:
        print(f"error: {bad}", file=sys.stderr)
        return 2
    info: dict = {}
    pair = camera = road = None
    if preset is not None:
        from fsof_torch.data.scene import PRESETS, render_pair

        if preset not in PRESETS:
            print(f"error: --preset: unknown preset {preset!r}; choose from {', '.join(sorted(PRESETS))}", file=sys.stderr)
            return 2
        pair = render_pair(preset, index, seed=seed, size=tuple(args.size) if args.size else None,
                           dtype=torch.float64)
        key = "flow" if args.model == "displacement" else "flow_velocity"
        flow, valid, road = pair[key][None], pair["valid"][None], pair["road"][None]
        camera = pair["camera"]
        mask = valid & road if args.road_only else valid
        info["source"] = {"preset": preset, "index": index, "seed": seed, "odometry": pair["odometry"],
                          "velocity": pair["velocity"], "size": list(flow.shape[-2:])}
    else:
        from fsof_torch.io import read_flow, read_road_mask

        if not args.flow.is_file():
            print(f"error: --flow: no file at {str(args.flow)!r}", file=sys.stderr)
            return 2
        try:
            flow, valid = read_flow(args.flow)
        except ValueError as err:  # (the reader's own argument, "path: ...", means nothing to the user)
            print(f"error: --flow: {str(err).removeprefix('path: ')}", file=sys.stderr)
            return 2
        flow, valid = flow[None].double(), valid[None]
        mask = valid
        if args.mask is not None:
            size = tuple(flow.shape[-2:])
            try:
                # a mask of another size (a PNG, or a polygon whose 'size' is another) is another
                # image's road, more likely another pair's than one to stretch: the reader refuses it
                mask = valid & read_road_mask(args.mask, size=size)[None]
            except (ValueError, TypeError, FileNotFoundError, IsADirectoryError) as err:  # (a folder: a traceback)
                print(f"error: --mask: {str(err).removeprefix('path: ')}", file=sys.stderr)
                return 2
        info["source"] = {"flow": str(args.flow), "mask": str(args.mask) if args.mask else None,
                          "size": list(flow.shape[-2:])}
    if not bool(mask.any()):
        # nothing to histogram or fit: a bad input, not a failed fit
        if args.mask is not None and preset is None:
            bad = f"--mask: {str(args.mask)!r} covers no pixel where {str(args.flow)!r} has valid flow"
        elif preset is None:
            bad = f"--flow: {str(args.flow)!r} has no valid flow pixel"
        else:
            bad = f"--preset: pair {index} of {preset!r} has no valid {'road ' if args.road_only else ''}pixel"
        print(f"error: {bad}", file=sys.stderr)
        return 2
    # the inputs are good: an earlier run's files go (freespace.png where this run draws none,
    # DIR/vflow.json where it writes its JSON elsewhere), not to be read as this run's
    remove_outputs(args.out, figures + ["vflow.json"])
    if args.json is not None:  # (and its JSON elsewhere: a run that stops would leave it as its own)
        remove_outputs(args.json.parent, [args.json.name])
    # (opened after the input checks, so that an error line never prints inside the bar's line; closed by its
    # with, so that an interruption's line, or a full disk's, starts on a line of its own)
    with progress_bar(total=len(steps), enabled=not args.no_progress, desc="vflow", unit="step") as bar:
        bar.update(1)
        unit = "px" if args.model == "displacement" else "px/s"
        hist, edges = vflow_map(flow, mask, bins=args.bins)
        bar.update(1)
        curve = fit_vflow_curve(flow, mask, model=args.model, statistic=args.statistic, bins=args.bins,
                                min_row_pixels=MIN_ROW_PIXELS, inlier_threshold=args.inlier_threshold,
                                relative_threshold=args.relative_threshold)
        bar.update(1)

        fv = flow[:, 1:2]
        in_fit = mask & curve.fitted_valid
        err = (fv - curve.fitted).abs()
        # the road: the preset's, or --mask (a road mask); without one (--flow alone) no road figure
        on_road = in_fit & road if road is not None else in_fit if args.mask is not None else None
        info["curve"] = {"model": args.model, "a": float(curve.a[0]), "v0": float(curve.v0[0]),
                         "success": bool(curve.success[0]), "row_residual": float(curve.residual[0]),
                         "inlier_rows": int(curve.row_inliers[0].sum()),
                         "used_rows": int((curve.row_support[0] >= MIN_ROW_PIXELS).sum()),
                         "nfa": float(curve.nfa[0]),
                         "inlier_threshold": args.inlier_threshold, "relative_threshold": args.relative_threshold,
                         "mean_abs_fv_error_mask": float(err[in_fit].mean()) if in_fit.any() else None,
                         "mean_abs_fv_error_road": float(err[on_road].mean())
                         if on_road is not None and on_road.any() else None,
                         "unit": unit}
        if camera is not None:
            name = "z_d_m" if args.model == "displacement" else "speed_mps"
            truth = pair["odometry"]["z_d"] if args.model == "displacement" else pair["velocity"]["speed"]
            info["curve"][name] = float(curve.scale(camera)[0])
            info["curve"][name + "_true"] = float(truth)
            info["curve"]["horizon_row_true"] = float(camera.horizon_row()[0])
        files = {"vflow_map": args.out / "vflow_map.png", "fv_observed": args.out / "fv_observed.png",
                 "fv_fitted": args.out / "fv_fitted.png", "fv_error": args.out / "fv_error.png"}
        if "freespace" in steps:
            found = detect_freespace(flow, camera, mask=valid, threshold=0.05, relative_threshold=0.02,
                                     return_details=True)
            free = found.freespace
            truth = road & valid
            inter, union = float((free & truth).sum()), float((free | truth).sum())
            info["freespace"] = {"success": bool(found.success[0]), "iou": inter / max(union, 1.0),
                                 "pixels": int(free.sum()),
                                 "road_pixels": int(truth.sum()), "z_d_m": float(found.fit.params["z_d"][0]),
                                 "threshold_px": 0.05, "relative_threshold": 0.02}
            files["freespace"] = args.out / "freespace.png"
            bar.update(1)

        args.out.mkdir(parents=True, exist_ok=True)
        _plot_map(hist[0], edges, curve, files["vflow_map"], unit)
        # Observed and fitted on one scale, the observed values' (the mask holds a pixel: checked above).
        lo, hi = _colour_range(fv[mask])
        _plot_image(fv[0, 0], mask[0, 0], files["fv_observed"], f"observed F_v ({unit}) in the mask", "RdBu_r", lo,
                    hi, f"F_v ({unit}; < 0 above the horizon)")
        _plot_image(curve.fitted[0, 0], curve.fitted_valid[0, 0], files["fv_fitted"], f"fitted F_v ({unit})",
                    "RdBu_r", lo, hi, f"F_v ({unit})")
        _plot_image(err[0, 0], in_fit[0, 0], files["fv_error"], f"|observed - fitted F_v| ({unit})", "inferno", 0.0,
                    error_vmax(err[in_fit]), f"|F_v error| ({unit})")
        if "freespace" in steps:
            _plot_freespace(pair["image1"], free[0], truth[0], files["freespace"], info["freespace"]["iou"])
        bar.update(1)

    info["files"] = {k: str(v) for k, v in files.items()}
    # (a given --flow drew no scene: no seed)
    info["environment"] = environment("vflow", args, seed=info["source"].get("seed"))
    json_path = args.json if args.json is not None else args.out / "vflow.json"
    write_json(make_parent(json_path), info)
    # (printed after the files are written: a reader of stdout that goes away (| head) loses none)
    c = info["curve"]
    print(f"\nV-flow curve ({args.model}): a = {c['a']:.6e} 1/{'px' if args.model == 'displacement' else '(px s)'}, "
          f"v0 = {c['v0']:.3f} px, success {c['success']}, "
          f"{'inlier rows' if c['success'] else 'rows near the rejected curve'} {c['inlier_rows']}/{c['used_rows']}, "
          f"false alarms {c['nfa']:.2g}")
    if camera is not None:
        name = "z_d_m" if args.model == "displacement" else "speed_mps"
        if c["success"]:
            print(f"  {name}: fitted {c[name]:.4f}, true {c[name + '_true']:.4f}; horizon row: fitted {c['v0']:.3f}, "
                  f"true {c['horizon_row_true']:.3f}")
        else:  # (its 0 is no fitted value)
            print(f"  {name}: not fitted, true {c[name + '_true']:.4f}; horizon row: true {c['horizon_row_true']:.3f}")
    if c["mean_abs_fv_error_road"] is not None:
        print(f"  mean |F_v - fitted| on the road: {c['mean_abs_fv_error_road']:.4f} {unit}"
              f" (all mask pixels: {c['mean_abs_fv_error_mask']:.4f})")
    elif c["mean_abs_fv_error_mask"] is not None:
        print(f"  mean |F_v - fitted| over the flow's valid pixels where the curve is defined (no road mask): "
              f"{c['mean_abs_fv_error_mask']:.4f} {unit}")
    if "freespace" in info:
        fs_info = info["freespace"]
        print(f"  freespace IoU with the road: {fs_info['iou']:.4f}, " + (f"its road model's z_d {fs_info['z_d_m']:.4f} m"
              if fs_info["success"] else "the detection failed: no freespace"))
    print(f"wrote {json_path}" + "".join(f", {p}" for p in files.values()))
    if not (c["success"] and math.isfinite(c["a"])):
        print("the V-flow curve could not be fitted (success false: too few inlier rows, no more than chance "
              f"gives ({c['nfa']:.2g} false alarms), or no finite curve)",
              file=sys.stderr)
        return 1
    return 0
