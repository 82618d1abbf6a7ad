"""The job's loop: per pair and flow source, predict, refine with each odometry variant, measure
before and after, write the refined flow, figures and a per-pair record; then the report.

Layout of ``--out`` (one folder per source and variant)::

    OUT/report.md, OUT/report.json
    OUT/<source>/before/<pair>_flow.png, <pair>_error.png, <pair>_road.png   (figures, prediction)
    OUT/<source>/<variant>/flow/<pair>.png           refined flow, KITTI 16-bit PNG
    OUT/<source>/<variant>/figures/<pair>_flow.png, <pair>_error.png        (after refinement)
    OUT/<source>/<variant>/pairs/<pair>.json         metrics before/after + fitted odometry

A pair's JSON record is written last, atomically: its presence marks the (source, variant, pair)
as finished, so an interrupted run resumes where it stopped (``--overwrite`` redoes everything).
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from fsof_torch.geometry.camera import Camera
from fsof_torch.refinement.fusion import FreespaceRefiner

from .inputs import JobError, PairSpec, odometry_from_pose
from .sources import make_source

VARIANTS = ("given", "given_pitch", "fit", "photometric")
VARIANT_HELP = {"given": "odometry given (scene / poses)",
                "given_pitch": "poses, with the camera pitch calibrated over the clip",
                "fit": "ego-motion fitted to the flow",
                "photometric": "ego-motion fitted to the images (started from the flow fit)"}


@dataclass
class JobConfig:
    out: Path
    sources: list[str]
    variants: list[str]
    mode: str = "replace"
    scale: float = 2.0
    fit_roll: bool = False
    fit_pitch: bool = False
    road_auto: bool = False
    overwrite: bool = False
    figures: bool = True
    progress: bool = True
    title: str = "refine"
    testnet_weights: Path | None = None
    calibrated_pitch_deg: float | None = None
    notes: list[str] = field(default_factory=list)


# -- measuring ------------------------------------------------------------------------------------

def evaluate(pair: dict, pred: Tensor, refined: Tensor, road: Tensor) -> tuple[dict, dict]:
    """Metrics of the prediction and of the refined flow on the same pixels.

    Photometric error (L1, 0..255 scale) over the pixels where both flows are finite and both
    sample points fall inside image2 (so that a flow that pushes pixels out of the image is not
    rewarded for it), inside the road and overall; with ground truth, e_E / e_A / Fl over the
    valid ground-truth pixels where the prediction is finite (KITTI style), and the photometric
    error once more over those pixels too (``photo_road_noc``, ``photo_all_noc``): a pixel
    occluded in image 2 has no true match, so no flow explains its brightness and the error
    there rewards a flow that points at a look-alike instead (on the synthetic scene the exact
    flow scores 24.9 on its occluded road pixels, DIS 10.4).
    """
    from fsof_torch.evaluation.metrics import flow_metrics
    from fsof_torch.evaluation.photometric import photometric_error_map

    im1, im2 = pair["image1"][None], pair["image2"][None]
    finite = (torch.isfinite(pred).all(dim=0, keepdim=True) & torch.isfinite(refined).all(dim=0, keepdim=True))[None]
    flows = {"before": torch.nan_to_num(pred)[None], "after": torch.nan_to_num(refined)[None]}
    maps = {k: photometric_error_map(im1, im2, f) for k, f in flows.items()}
    common = finite & maps["before"][1] & maps["after"][1]
    regions = [("road", common & road[None]), ("all", common)]
    if pair.get("gt") is not None:
        noc = pair["gt"][1][None]
        regions += [("road_noc", common & road[None] & noc), ("all_noc", common & noc)]
    out: dict[str, dict] = {"before": {}, "after": {}}
    for stage, (err, _) in maps.items():
        for region, mask in regions:
            n = int(mask.sum())
            out[stage][f"photo_{region}"] = float(err[mask].double().sum()) / max(n, 1)
            out[stage][f"photo_{region}_n"] = n
    if pair.get("gt") is not None:
        gt, valid = pair["gt"]
        for stage, f in flows.items():
            for region, mask in (("road", road[None] & finite), ("all", finite)):
                m = flow_metrics(f, gt[None].to(f.dtype), mask, valid[None])
                out[stage][f"epe_{region}"] = m["e_E"]
                out[stage][f"ae_{region}"] = m["e_A"]
                out[stage][f"fl_{region}"] = m["Fl"]
                out[stage][f"epe_{region}_n"] = m["n_pixels"]
    return out["before"], out["after"]


def error_map(pair: dict, flow: Tensor) -> tuple[Tensor, Tensor, str]:
    """The per-pixel map shown in figures: end-point error with ground truth, else photometric."""
    f = torch.nan_to_num(flow)[None]
    if pair.get("gt") is not None:
        gt, valid = pair["gt"]
        return (f[0] - gt).norm(dim=0, keepdim=True), valid, "epe"
    from fsof_torch.evaluation.photometric import photometric_error_map

    err, valid = photometric_error_map(pair["image1"][None], pair["image2"][None], f)
    return err[0], valid[0], "photo"


# -- the loop -------------------------------------------------------------------------------------

def _paths(cfg: JobConfig, source: str, variant: str, name: str) -> dict[str, Path]:
    base = cfg.out / source / variant
    return {"flow": base / "flow" / f"{name}.png", "record": base / "pairs" / f"{name}.json",
            "fig_flow": base / "figures" / f"{name}_flow.png",
            "fig_error": base / "figures" / f"{name}_error.png"}


def _done(cfg: JobConfig, source: str, variant: str, name: str) -> bool:
    if cfg.overwrite:
        return False
    p = _paths(cfg, source, variant, name)
    return p["record"].is_file() and p["flow"].is_file()


def _camera_for(variant: str, camera: Camera, cfg: JobConfig) -> Camera:
    if variant == "given_pitch":
        if cfg.calibrated_pitch_deg is None:
            raise JobError("--odometry given_pitch needs --calibrate-pitch (and --poses)")
        return camera.replace(pitch=math.radians(cfg.calibrated_pitch_deg))
    return camera


def _odometry(variant: str, pair: dict, camera: Camera) -> dict | None:
    if variant not in ("given", "given_pitch"):
        return None
    if pair.get("relative_pose") is not None:
        return odometry_from_pose(pair["relative_pose"], camera)
    if pair.get("odometry") is None:
        raise JobError("--odometry given: this pair has no odometry (give --poses, or use a synthetic scene)")
    return pair["odometry"]


def run_pairs(specs: list[PairSpec], cfg: JobConfig, *, camera: Camera | None = None) -> list[dict]:
    """Process every (pair, source, variant) not yet finished; return all records (old and new).

    ``camera`` replaces the pairs' own camera (e.g. with a calibrated pitch)."""
    from fsof_torch.io import write_json, write_kitti_flow

    for source in cfg.sources:
        for variant in cfg.variants:
            for key in ("flow", "record", "fig_flow"):
                _paths(cfg, source, variant, "x")[key].parent.mkdir(parents=True, exist_ok=True)
        (cfg.out / source / "before").mkdir(parents=True, exist_ok=True)

    sources = {}
    refiners = {v: FreespaceRefiner(mode=cfg.mode, scale=cfg.scale,
                                    fit="photometric" if v == "photometric" else "flow",
                                    fit_roll=cfg.fit_roll, fit_pitch=cfg.fit_pitch, warn=False)
                for v in cfg.variants}
    from tqdm import tqdm

    bar = tqdm(specs, desc=cfg.title, unit="pair", disable=not cfg.progress, file=sys.stderr)
    for spec in bar:
        todo = [(s, v) for s in cfg.sources for v in cfg.variants if not _done(cfg, s, v, spec.name)]
        if not todo:
            continue
        pair = spec.load()
        cam = (camera if camera is not None else pair["camera"]).to(torch.float64)
        for source in dict.fromkeys(s for s, _ in todo):
            if source not in sources:
                sources[source] = make_source(source, weights=cfg.testnet_weights)
            pred = sources[source](pair, spec.flow_files.get("files"))
            road, road_from = _road(pair, pred, cam, cfg)
            if cfg.figures:
                _figures_before(cfg, source, spec.name, pair, pred, road)
            for variant in [v for s, v in todo if s == source]:
                bar.set_postfix_str(f"{spec.name} {source}/{variant}")
                record = _refine_one(cfg, refiners[variant], source, variant, spec.name, pair, pred,
                                     road, _camera_for(variant, cam, cfg), road_from)
                paths = _paths(cfg, source, variant, spec.name)
                flow = record.pop("_flow")
                finite = torch.isfinite(flow).all(dim=0, keepdim=True)
                write_kitti_flow(paths["flow"], torch.nan_to_num(flow), finite)
                if cfg.figures:
                    _figures_after(paths, pair, flow, before_flow=pred)
                write_json(paths["record"], record)
    return collect_records(cfg, [s.name for s in specs])


def _road(pair: dict, pred: Tensor, camera: Camera, cfg: JobConfig) -> tuple[Tensor, str]:
    if pair.get("road") is not None and not cfg.road_auto:
        return pair["road"].to(torch.bool), "given"
    from fsof_torch import detect_freespace

    f = torch.nan_to_num(pred)[None].to(torch.float64)
    H = pred.shape[-2]
    # A flow method is least reliable on the road right in front of the car (large motion, weak
    # texture): let the freespace start anywhere in the bottom eighth, and accept 1 px / 10 %.
    with torch.no_grad():
        mask = detect_freespace(f, camera, mask=torch.isfinite(pred).all(0, keepdim=True)[None],
                                bottom_rows=max(1, H // 8), threshold=1.0, relative_threshold=0.1)
    return mask[0], "auto"


def _refine_one(cfg: JobConfig, refiner: FreespaceRefiner, source: str, variant: str, name: str,
                pair: dict, pred: Tensor, road: Tensor, camera: Camera, road_from: str) -> dict:
    odo = _odometry(variant, pair, camera)
    images = (pair["image1"][None], pair["image2"][None]) if variant == "photometric" else None
    out = refiner(pred[None], road[None], camera, odo, images=images)
    flow = out.flow[0].detach()
    before, after = evaluate(pair, pred, flow, road)
    record: dict[str, Any] = {
        "pair": name, "source": source, "variant": variant, "mode": cfg.mode, "road": road_from,
        "road_pixels": int(road.sum()), "refined": bool(out.refined[0]),
        "odometry": {k: float(v[0]) for k, v in out.odometry.items()},
        "roll": float(out.camera.roll[0]), "pitch": float(out.camera.pitch[0]),
        "before": before, "after": after, "_flow": flow,
    }
    if pair.get("odometry") is not None or pair.get("relative_pose") is not None:
        record["odometry_given"] = _odometry("given", pair, camera)
    if out.fit is not None:
        record["fit_success"] = bool(out.fit.success.all())
        record["fit_residual_px"] = float(out.fit.residual[0])
    return record


# -- figures --------------------------------------------------------------------------------------

def _figures_before(cfg: JobConfig, source: str, name: str, pair: dict, pred: Tensor, road: Tensor) -> None:
    from fsof_torch.evaluation.visualize import save_error_png, save_flow_png, save_overlay_png

    base = cfg.out / source / "before"
    max_flow = _max_flow(pair, pred)
    save_flow_png(base / f"{name}_flow.png", torch.nan_to_num(pred), max_flow=max_flow)
    err, valid, _ = error_map(pair, pred)
    save_error_png(base / f"{name}_error.png", err, _vmax(pair), valid=valid)
    save_overlay_png(base / f"{name}_road.png", pair["image1"], road)
    if pair.get("gt") is not None and not (cfg.out / f"gt_{name}.png").exists():
        save_flow_png(cfg.out / f"gt_{name}.png", pair["gt"][0], max_flow=max_flow, valid=pair["gt"][1])


def _figures_after(paths: dict, pair: dict, flow: Tensor, *, before_flow: Tensor) -> None:
    from fsof_torch.evaluation.visualize import save_error_png, save_flow_png

    save_flow_png(paths["fig_flow"], torch.nan_to_num(flow), max_flow=_max_flow(pair, before_flow))
    err, valid, _ = error_map(pair, flow)
    save_error_png(paths["fig_error"], err, _vmax(pair), valid=valid)


def _max_flow(pair: dict, pred: Tensor) -> float:
    """One colour scale for before/after/ground truth: the ground truth's largest magnitude, or
    the prediction's 99th percentile (a few wild vectors would wash the picture out)."""
    if pair.get("gt") is not None:
        gt, valid = pair["gt"]
        mag = gt.norm(dim=0, keepdim=True)[valid]
    else:
        mag = torch.nan_to_num(pred).norm(dim=0).flatten()
    return max(float(torch.quantile(mag.float(), 0.99)) if mag.numel() else 1.0, 1.0)


def _vmax(pair: dict) -> float:
    return 5.0 if pair.get("gt") is not None else 50.0  # px of end-point error / grey levels


# -- records and the report -----------------------------------------------------------------------

def collect_records(cfg: JobConfig, names: list[str]) -> list[dict]:
    records = []
    for source in cfg.sources:
        for variant in cfg.variants:
            for name in names:
                p = _paths(cfg, source, variant, name)["record"]
                if p.is_file():
                    records.append(json.loads(p.read_text()))
    return records


def _weighted(records: list[dict], stage: str, key: str) -> float | None:
    """Mean over all counted pixels of the set (KITTI style), from per-pair means and counts."""
    num = den = 0.0
    for r in records:
        m = r[stage]
        if key in m and m.get(f"{key}_n", 0):
            num += m[key] * m[f"{key}_n"]
            den += m[f"{key}_n"]
    return num / den if den else None


METRICS = (("photo_road", "photometric error, road (0-255)"), ("photo_all", "photometric error, all"),
           ("photo_road_noc", "photometric error, non-occluded road (0-255)"),
           ("photo_all_noc", "photometric error, non-occluded (0-255)"),
           ("epe_road", "end-point error, road (px)"), ("epe_all", "end-point error, all (px)"))


def summarize(records: list[dict], cfg: JobConfig) -> dict:
    rows = []
    for source in cfg.sources:
        for variant in cfg.variants:
            rs = [r for r in records if r["source"] == source and r["variant"] == variant]
            if not rs:
                continue
            row: dict[str, Any] = {"source": source, "variant": variant, "pairs": len(rs),
                                   "refined": sum(r["refined"] for r in rs)}
            for key, _ in METRICS:
                b, a = _weighted(rs, "before", key), _weighted(rs, "after", key)
                if b is None or a is None:
                    continue
                row[f"{key}_before"] = b
                row[f"{key}_after"] = a
                row[f"{key}_change_pct"] = 100.0 * (a - b) / b if b else None
            odo_err = [abs(r["odometry"]["z_d"] - r["odometry_given"]["z_d"]) for r in rs
                       if variant in ("fit", "photometric") and "odometry_given" in r]
            if odo_err:
                row["z_d_abs_error_m"] = sum(odo_err) / len(odo_err)
            rows.append(row)
    return {"title": cfg.title, "mode": cfg.mode, "scale_px": cfg.scale, "rows": rows,
            "notes": cfg.notes, "pairs": records}


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None:
        return "–"
    if isinstance(x, float):
        return f"{x:.{digits}f}" if math.isfinite(x) else str(x)
    return str(x)


def table_markdown(summary: dict) -> str:
    have_epe = any("epe_all_before" in r for r in summary["rows"])
    have_noc = any("photo_road_noc_before" in r for r in summary["rows"])
    head = ["source", "odometry", "pairs", "photo road before", "after", "Δ%"]
    if have_noc:
        head += ["photo road noc before", "after", "Δ%"]
    head += ["photo all before", "after"]
    if have_epe:
        head += ["EPE road before", "after", "Δ%", "EPE all before", "after"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in summary["rows"]:
        cells = [r["source"], r["variant"], f'{r["refined"]}/{r["pairs"]}',
                 _fmt(r.get("photo_road_before")), _fmt(r.get("photo_road_after")),
                 _fmt(r.get("photo_road_change_pct"), 1)]
        if have_noc:
            cells += [_fmt(r.get("photo_road_noc_before")), _fmt(r.get("photo_road_noc_after")),
                      _fmt(r.get("photo_road_noc_change_pct"), 1)]
        cells += [_fmt(r.get("photo_all_before")), _fmt(r.get("photo_all_after"))]
        if have_epe:
            cells += [_fmt(r.get("epe_road_before")), _fmt(r.get("epe_road_after")),
                      _fmt(r.get("epe_road_change_pct"), 1), _fmt(r.get("epe_all_before")),
                      _fmt(r.get("epe_all_after"))]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(summary: dict, cfg: JobConfig, json_path: Path | None) -> str:
    from fsof_torch.io import write_json, write_text

    table = table_markdown(summary)
    md = [f"# {summary['title']}", "",
          f"Fusion mode: `{summary['mode']}`. Photometric error: mean |I1 − warp(I2, flow)| on the "
          "0–255 scale over the pixels where the sample points of both the prediction and the "
          "refined flow fall inside image 2 (the same pixels before and after); with ground truth also over "
          "the non-occluded ones only ('noc': the valid ground-truth pixels, where end-point error is "
          "measured; an occluded pixel has no true match). End-point error against the ground truth (KITTI "
          "style, over all valid pixels of the set). 'road' is the road mask the refiner used. "
          "'pairs' counts refined/processed pairs.", "", table, ""]
    md += [f"- {n}" for n in summary["notes"]]
    md += ["", "Odometry variants: " + "; ".join(f"`{k}`: {v}" for k, v in VARIANT_HELP.items()), ""]
    write_text(cfg.out / "report.md", "\n".join(md))
    write_json(cfg.out / "report.json", summary)
    if json_path is not None:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        write_json(json_path, summary)
    return table
