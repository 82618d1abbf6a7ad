"""The job's loop: per pair and flow source, predict, refine with each odometry variant, measure
before and after, write the refined flow, a figure and a per-pair record.

Layout of ``--out``::

    OUT/run.json                                   the run's identity and fingerprint
    OUT/report.md, OUT/report.json                 the report (written last)
    OUT/<source>/summary.png                       the clip over its pairs (figures on)
    OUT/<source>/figures/<pair>.png                before and after, flow and error (figures on)
    OUT/<source>/<variant>/flow/<pair>.png         refined flow, KITTI 16-bit PNG
    OUT/<source>/<variant>/pairs/<pair>.json       metrics before/after, odometry, fingerprints

A pair's JSON record is written last, atomically: its presence, with the run's fingerprint and
the pair's input fingerprint, marks the (source, variant, pair) as finished, so an interrupted
run resumes where it stopped (``--overwrite`` redoes everything).
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

from fsof_torch import Camera, FreespaceRefiner

from .inputs import JobError, PairSpec, odometry_from_pose

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
    calibrated_pitch_deg: float | None = None
    notes: list[str] = field(default_factory=list)
    fingerprint: str = ""
    device: str = "cpu"


# -- measuring ------------------------------------------------------------------------------------

def flow_maps(pair: dict, flow: Tensor) -> dict[str, Tensor]:
    """The per-pixel maps of one flow (2, H, W), computed once and reduced over any region:
    ``finite`` (1, H, W), the photometric error ``photo`` (|I1 − warp(I2, flow)|, 0..255) with
    ``in_bounds``; with ground truth ``e_E`` (px), ``e_A`` (rad), ``Fl`` (0/1) and ``gt_valid``."""
    from fsof_torch import photometric_error_map
    from fsof_torch.evaluation.metrics import flow_error_maps

    finite = torch.isfinite(flow).all(dim=0, keepdim=True)
    f = torch.nan_to_num(flow)[None]
    err, in_bounds = photometric_error_map(pair["image1"][None], pair["image2"][None], f)
    maps = {"flow": f[0], "finite": finite, "photo": err[0], "in_bounds": in_bounds[0]}
    if pair.get("gt") is not None:
        gt, valid = pair["gt"]
        errors, counted = flow_error_maps(f, gt[None].to(f.dtype), None, valid[None])
        maps.update({"e_E": errors["e_E"][0], "e_A": errors["e_A"][0], "Fl": errors["Fl"][0],
                     "gt_valid": counted[0]})
    return maps


def _mean(x: Tensor, mask: Tensor) -> tuple[float, int]:
    """Mean of ``x`` over ``mask`` (float64 sum, no boolean indexing) and the pixel count."""
    n = int(mask.sum())
    total = float(torch.where(mask, x, torch.zeros((), dtype=x.dtype, device=x.device)).sum(dtype=torch.float64))
    return total / max(n, 1), n


def compare(before: dict[str, Tensor], after: dict[str, Tensor], road: Tensor) -> tuple[dict, dict]:
    """Metrics of the prediction and of the refined flow on the same pixels.

    Photometric error (L1, 0..255 scale) over the pixels where both flows are finite and both
    sample points fall inside image2 (so that a flow that pushes pixels out of the image is not
    rewarded for it), inside the road and overall; with ground truth, e_E / e_A / Fl over the
    valid ground-truth pixels where both flows are finite (KITTI style), and the photometric
    error once more over those pixels (``photo_road_noc``, ``photo_all_noc``): a pixel occluded
    in image 2 has no true match, so no flow explains its brightness and the error there rewards
    a flow that points at a look-alike instead (on the synthetic scene the exact flow scores 24.9
    on its occluded road pixels, DIS 10.4).
    """
    finite = before["finite"] & after["finite"]
    common = finite & before["in_bounds"] & after["in_bounds"]
    regions = [("road", common & road), ("all", common)]
    gt = "gt_valid" in before
    if gt:
        noc = before["gt_valid"]
        regions += [("road_noc", common & road & noc), ("all_noc", common & noc)]
        epe_regions = [("road", road & finite & noc), ("all", finite & noc)]
    out: tuple[dict, dict] = ({}, {})
    for stage, maps in zip(out, (before, after)):
        for region, mask in regions:
            stage[f"photo_{region}"], stage[f"photo_{region}_n"] = _mean(maps["photo"], mask)
        if gt:
            for region, mask in epe_regions:
                stage[f"epe_{region}"], stage[f"epe_{region}_n"] = _mean(maps["e_E"], mask)
                stage[f"ae_{region}"], _ = _mean(maps["e_A"], mask)
                stage[f"fl_{region}"], _ = _mean(maps["Fl"], mask)
    return out


def evaluate(pair: dict, pred: Tensor, refined: Tensor, road: Tensor) -> tuple[dict, dict]:
    """:func:`compare` of a prediction and its refinement (both (2, H, W)); ``road`` (1, H, W)."""
    return compare(flow_maps(pair, pred), flow_maps(pair, refined), road)


def error_panel(maps: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
    """The map a figure shows for a flow: end-point error with ground truth, else photometric."""
    if "e_E" in maps:
        return maps["e_E"], maps["gt_valid"] & maps["finite"]
    return maps["photo"], maps["in_bounds"] & maps["finite"]


def max_flow(pair: dict, pred: Tensor, road: Tensor | None = None) -> float:
    """One colour scale for before and after: the 99th percentile of the ground truth's magnitude
    over its valid pixels, or of the prediction's, inside the road when ``road`` (1, H, W) has
    pixels (the road is what the figures are about; the much larger flow of nearby buildings
    would wash it out), else over the image."""
    if pair.get("gt") is not None:
        flow, valid = pair["gt"]
    else:
        flow = torch.nan_to_num(pred, nan=0.0, posinf=0.0, neginf=0.0)
        valid = torch.isfinite(pred).all(dim=0, keepdim=True)
    if road is not None and bool((valid & road).any()):
        valid = valid & road
    mag = torch.where(valid[0], torch.hypot(flow[0], flow[1]), torch.full((), -1.0, dtype=flow.dtype)).flatten()
    n_valid = int(valid.sum())
    if n_valid == 0:
        return 1.0
    k = mag.numel() - n_valid + max(1, math.ceil(0.99 * n_valid))  # the invalid -1s sort first
    return max(float(mag.kthvalue(k).values), 1.0)


# -- the loop -------------------------------------------------------------------------------------

def paths(cfg: JobConfig, source: str, variant: str, name: str) -> dict[str, Path]:
    base = cfg.out / source / variant
    return {"flow": base / "flow" / f"{name}.png", "record": base / "pairs" / f"{name}.json"}


def figure_path(cfg: JobConfig, source: str, name: str) -> Path:
    return cfg.out / source / "figures" / f"{name}.png"


def read_record(cfg: JobConfig, source: str, variant: str, spec: PairSpec, input_fp: str) -> dict | None:
    """The pair's record if it was written by a run of this fingerprint on these inputs."""
    p = paths(cfg, source, variant, spec.name)
    if not (p["record"].is_file() and p["flow"].is_file()):
        return None
    try:
        record = json.loads(p["record"].read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        return None
    if record.get("fingerprint") != cfg.fingerprint or record.get("input_fingerprint") != input_fp:
        return None
    return record


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


def run_pairs(specs: list[PairSpec], cfg: JobConfig, sources: dict, *, rank: int = 0,
              camera: Camera | None = None) -> list[dict]:
    """Process every (pair, source, variant) of ``specs`` not yet finished; return their records
    (old and new, each with ``rank`` and ``resumed``).

    ``sources`` maps a source name to its callable (:func:`refine.sources.make_source`);
    ``camera`` replaces the pairs' own camera (e.g. with a calibrated pitch)."""
    from fsof_torch.io import write_json, write_kitti_flow
    from tqdm import tqdm

    for source in cfg.sources:
        for variant in cfg.variants:
            for p in paths(cfg, source, variant, "x").values():
                p.parent.mkdir(parents=True, exist_ok=True)
        if cfg.figures:
            figure_path(cfg, source, "x").parent.mkdir(parents=True, exist_ok=True)
    refiners = {v: FreespaceRefiner(mode=cfg.mode, scale=cfg.scale,
                                    fit="photometric" if v == "photometric" else "flow",
                                    fit_roll=cfg.fit_roll, fit_pitch=cfg.fit_pitch, warn=False)
                for v in cfg.variants}
    records: list[dict] = []
    bar = tqdm(specs, desc="refine", unit="pair", disable=not cfg.progress, file=sys.stderr, dynamic_ncols=True)
    for spec in bar:
        bar.set_postfix_str(f"{spec.name}: checking earlier results")
        input_fp = _input_fingerprint(spec)
        done = {(s, v): read_record(cfg, s, v, spec, input_fp) for s in cfg.sources for v in cfg.variants}
        todo = [s for s in cfg.sources
                if cfg.overwrite or any(done[(s, v)] is None for v in cfg.variants)
                or (cfg.figures and not figure_path(cfg, s, spec.name).is_file())]
        for s in cfg.sources:
            if s not in todo:
                records += [{**done[(s, v)], "resumed": True} for v in cfg.variants]
        if not todo:
            continue
        bar.set_postfix_str(f"{spec.name}: loading the pair")
        pair = _to_device(spec.load(), cfg.device)
        cam = (camera if camera is not None else pair["camera"]).to(torch.float64)
        for source in todo:
            bar.set_postfix_str(f"{spec.name}: predicting flow ({source})")
            pred = sources[source](pair, spec.flow_files.get("files")).to(cfg.device)
            bar.set_postfix_str(f"{spec.name}: road mask and errors before ({source})")
            road, road_from, road_info = _road(pair, pred, cam, cfg)
            before = flow_maps(pair, pred)
            flows, maps = {}, {}
            for variant in cfg.variants:
                bar.set_postfix_str(f"{spec.name}: refining {source} with odometry '{variant}'")
                record, flow, after = _refine_one(cfg, refiners[variant], pair, pred, road,
                                                  _camera_for(variant, cam, cfg), variant, before)
                record.update({"pair": spec.name, "source": source, "variant": variant, "mode": cfg.mode,
                               "road": road_from, **road_info, "rank": rank, "fingerprint": cfg.fingerprint,
                               "input_fingerprint": input_fp})
                p = paths(cfg, source, variant, spec.name)
                finite = torch.isfinite(flow).all(dim=0, keepdim=True)
                write_kitti_flow(p["flow"], torch.nan_to_num(flow).cpu(), finite.cpu())
                write_json(p["record"], record)
                records.append({**record, "resumed": False})
                flows[variant], maps[variant] = flow, after
            if cfg.figures:
                bar.set_postfix_str(f"{spec.name}: drawing the figure ({source})")
                _figure(cfg, source, spec.name, pair, pred, road, before, flows, maps)
    bar.close()
    return records


def _to_device(pair: dict, device: str) -> dict:
    """The pair's tensors on ``device`` (the camera moves with the refiner)."""
    if device == "cpu":
        return pair
    out = dict(pair)
    for k in ("image1", "image2", "road"):
        if isinstance(out.get(k), Tensor):
            out[k] = out[k].to(device)
    if out.get("gt") is not None:
        out["gt"] = tuple(t.to(device) for t in out["gt"])
    return out


def _input_fingerprint(spec: PairSpec) -> str:
    from .resume import fingerprint

    return fingerprint({"pair": spec.name, **spec.identity()})


def _road(pair: dict, pred: Tensor, camera: Camera, cfg: JobConfig) -> tuple[Tensor, str, dict]:
    """The road mask, where it came from, and with ``--road auto`` the detection's flag, reason and
    coverage (recorded per pair: a flagged pair is left unrefined, never silently)."""
    if pair.get("road") is not None and not cfg.road_auto:
        return pair["road"].to(torch.bool), "given", {}
    from fsof_torch import detect_road

    finite = bool(torch.isfinite(pred).all())
    with torch.no_grad():
        det = detect_road(pair["image1"][None], pair["image2"][None], camera, flow=pred[None] if finite else None)
    info = {"road_flag": det.flag[0], "road_reason": det.reason[0], "road_coverage": float(det.coverage[0]),
            "road_auto_pixels": int(det.mask.sum())}
    return det.usable_mask[0], "auto", info


def _refine_one(cfg: JobConfig, refiner: FreespaceRefiner, pair: dict, pred: Tensor, road: Tensor,
                camera: Camera, variant: str, before: dict) -> tuple[dict, Tensor, dict]:
    odo = _odometry(variant, pair, camera)
    images = (pair["image1"][None], pair["image2"][None]) if variant == "photometric" else None
    out = refiner(pred[None], road[None], camera, odo, images=images)
    flow = out.flow[0].detach()
    after = flow_maps(pair, flow)
    m_before, m_after = compare(before, after, road)
    record: dict[str, Any] = {
        "road_pixels": int(road.sum()), "refined": bool(out.refined[0]),
        "odometry": {k: float(v[0]) for k, v in out.odometry.items()},
        "roll": float(out.camera.roll[0]), "pitch": float(out.camera.pitch[0]),
        "before": m_before, "after": m_after,
    }
    if pair.get("odometry") is not None or pair.get("relative_pose") is not None:
        record["odometry_given"] = _odometry("given", pair, camera)
    if out.fit is not None:
        record["fit_success"] = bool(out.fit.success.all())
        record["fit_residual_px"] = float(out.fit.residual[0])
    return record, flow, after


def _figure(cfg: JobConfig, source: str, name: str, pair: dict, pred: Tensor, road: Tensor,
            before: dict, flows: dict[str, Tensor], maps: dict[str, dict]) -> None:
    from fsof_torch.evaluation.figures import pair_figure, save_figure

    gt = pair.get("gt") is not None
    label = "end-point error (px)" if gt else "photometric error (grey levels)"
    columns = {f"before ({source})": (pred, before)}
    columns.update({f"after, odometry '{v}'": (flows[v], maps[v]) for v in flows})
    cpu = lambda t: t.detach().cpu()  # noqa: E731
    fig = pair_figure(images=(cpu(pair["image1"]), cpu(pair["image2"])),
                      flows={k: cpu(f) for k, (f, _) in columns.items()},
                      errors={k: tuple(cpu(t) for t in error_panel(m)) for k, (_, m) in columns.items()},
                      road=cpu(road), max_flow=max_flow(pair, pred, road), error_vmax=5.0 if gt else 50.0,
                      error_label=label,
                      title=f"pair {name}, flow source '{source}': flow and error before and after "
                            f"refinement (mode '{cfg.mode}'); error: "
                            + ("|flow − ground truth|" if gt else "|I1 − I2 warped by the flow|, 0–255"))
    save_figure(fig, figure_path(cfg, source, name))
