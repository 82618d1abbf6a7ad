"""The job's loop: per pair and flow source, predict, refine with each odometry variant, measure
before and after, write the refined flow, a figure and a per-pair record.

Layout of ``--out``::

    OUT/run.json                                   the run's identity and fingerprint
    OUT/report.md, OUT/report.json                 the report (removed first, written last)
    OUT/<source>/summary.png                       the clip over its pairs (figures on; as the report)
    OUT/<source>/figures/<pair>.png                before and after, flow and error (figures on)
    OUT/<source>/<variant>/flow/<pair>.png         refined flow, KITTI 16-bit PNG (pixels beyond its
                                                   ±512 px marked invalid, counted in the record)
    OUT/<source>/<variant>/pairs/<pair>.json       metrics before/after, odometry, fingerprints

A pair's JSON record is written last, atomically: its presence, with the run's fingerprint, the
pair's input fingerprint and the digest of the flow file beside it (``flow_digest``, the file's
current one), marks the (source, variant, pair) as finished, so an interrupted
run resumes where it stopped (``--overwrite`` redoes everything). A pair's figure is removed
before its source's records are rewritten and drawn after them, so a figure never shows older
records than the pair's (with figures on, a pair without its figure is redone).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from fsof_torch import Camera, FreespaceRefiner, ImageMotionEstimator

from .inputs import JobError, PairSpec, file_digest, odometry_from_pose
from .measure import compare, error_panel, flow_maps, max_flow

VARIANTS = ("given", "given_images", "given_pitch", "fit", "photometric", "sequence")
VARIANT_HELP = {"given": "odometry given (scene / poses), the paper's model alone",
                "given_images": "odometry given fixes the planar motion (with --odometry-sigma: within those "
                                "widths), the images estimate the rest (the camera's attitude over the road, its "
                                "changes, vertical motion)",
                "given_pitch": "odometry given, with the camera's mounting calibrated over the clip",
                "fit": "ego-motion fitted to the predicted flow",
                "photometric": "road motion estimated from the two images (the refiner's default with images)",
                "sequence": "road motion of the clip from its images: mounting calibrated over the clip, "
                            "motion carried forward, attitude smoothed"}
#: the variants whose refiner sees the images (and judges the model by them)
WITH_IMAGES = ("given_images", "photometric", "sequence")


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
    calibrate: bool = False
    odometry_sigma: dict | None = None  # given_images: ImageMotionEstimator's (None: the odometry held fixed)
    fit_options: dict = field(default_factory=dict)  # fit_image's, for the road motion from the images
    road_options: dict = field(default_factory=dict)  # detect_road's, for --road auto
    clip: Any = None  # refine.calibrate.ClipFit: the clip's road motion and calibrated camera
    clip_fingerprint: str = ""  # the inputs of every pair of the clip
    notes: list[str] = field(default_factory=list)
    fingerprint: str = ""
    device: str = "cpu"


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
    if not isinstance(record, dict):  # JSON, but not a record: redone, as an unreadable one
        return None
    if record.get("fingerprint") != cfg.fingerprint or record.get("input_fingerprint") != input_fp:
        return None
    # the flow beside it must be the one it was written with (not truncated, nor another run's
    # copied in its place); a record of a version that did not store the digest is taken as it is
    if "flow_digest" in record and record["flow_digest"] != file_digest(p["flow"]):
        return None
    return record


def _uses_clip(variant: str, cfg: JobConfig) -> bool:
    return variant in ("given_pitch", "sequence") or cfg.calibrate


def _camera_for(variant: str, camera: Camera, cfg: JobConfig) -> Camera:
    """The camera of a variant: the clip's calibrated one with --calibrate-pitch, for
    ``given_pitch`` and for ``sequence`` (whose motion refers to it)."""
    if _uses_clip(variant, cfg):
        if cfg.clip is None:
            raise JobError(f"--odometry {variant} needs a clip (consecutive frames) to calibrate over")
        return cfg.clip.camera.to(camera.K.dtype)
    return camera


def _odometry(variant: str, pair: dict, camera: Camera, cfg: JobConfig | None = None,
              name: str | None = None) -> dict | None:
    if variant == "sequence":
        return cfg.clip.motion[name]
    if variant not in ("given", "given_images", "given_pitch"):
        return None
    if pair.get("relative_pose") is not None:
        return odometry_from_pose(pair["relative_pose"], camera)
    if pair.get("odometry") is None:
        raise JobError(f"--odometry {variant}: this pair has no odometry (give --poses, or use a synthetic scene)")
    return pair["odometry"]


def _refiner(variant: str, cfg: JobConfig) -> FreespaceRefiner:
    """The refiner of a variant: ``fit`` fits the flow; ``given_images`` with ``--odometry-sigma``
    lets the images move the odometry; the others are the default refiner."""
    common = {"mode": cfg.mode, "scale": cfg.scale, "warn": False}
    if variant == "fit":
        return FreespaceRefiner(fit="flow", fit_roll=cfg.fit_roll, fit_pitch=cfg.fit_pitch, **common)
    if variant in ("photometric", "given_images"):  # (the refiner's own estimator, with the job's options)
        sigma = cfg.odometry_sigma if variant == "given_images" else None
        return FreespaceRefiner(estimator=ImageMotionEstimator(odometry_sigma=sigma, **cfg.fit_options), **common)
    return FreespaceRefiner(**common)


def run_pairs(specs: list[PairSpec], cfg: JobConfig, sources: dict, *, rank: int = 0,
              camera: Camera | None = None) -> list[dict]:
    """Process every (pair, source, variant) of ``specs`` not yet finished; return their records
    (old and new, each with ``rank`` and ``resumed``).

    ``sources`` maps a source name to its callable (:func:`refine.sources.make_source`);
    ``camera`` replaces the pairs' own camera (e.g. with a calibrated pitch)."""
    from fsof_torch.io import write_json

    from fsof_torch.io.progress import progress_bar, show_text

    for source in cfg.sources:
        for variant in cfg.variants:
            for p in paths(cfg, source, variant, "x").values():
                p.parent.mkdir(parents=True, exist_ok=True)
        if cfg.figures:
            figure_path(cfg, source, "x").parent.mkdir(parents=True, exist_ok=True)
    refiners = {v: _refiner(v, cfg) for v in cfg.variants}
    records: list[dict] = []
    figures: dict[tuple, Any] = {}  # a PairFigure per layout, redrawn for every pair
    bar = progress_bar(specs, enabled=cfg.progress, desc="refine", unit="pair", dynamic_ncols=True)
    try:
        for spec in bar:
            show_text(bar, f"{spec.name}: checking earlier results")
            pair_fp = input_fingerprint(spec)
            # a variant that rests on the clip's fit depends on every frame of the clip
            input_fp = {v: pair_fp + ":" + cfg.clip_fingerprint if _uses_clip(v, cfg) else pair_fp
                        for v in cfg.variants}
            done = {(s, v): read_record(cfg, s, v, spec, input_fp[v]) for s in cfg.sources for v in cfg.variants}
            todo = [s for s in cfg.sources
                    if cfg.overwrite or any(done[(s, v)] is None for v in cfg.variants)
                    or (cfg.figures and not figure_path(cfg, s, spec.name).is_file())]
            for s in cfg.sources:
                if s not in todo:
                    records += [{**done[(s, v)], "resumed": True} for v in cfg.variants]
            if not todo:
                continue
            show_text(bar, f"{spec.name}: loading the pair")
            pair = _to_device(spec.load(), cfg.device)
            cam = (camera if camera is not None else pair["camera"]).to(torch.float64)
            show_text(bar, f"{spec.name}: road mask")
            road, road_from, road_info, dis_pred = _pair_road(pair, cam, cfg, sources, spec.name)
            for source in todo:
                show_text(bar, f"{spec.name}: predicting flow ({source})")
                if source == "dis" and dis_pred is not None:  # already predicted for the road
                    pred = dis_pred
                else:
                    pred = sources[source](pair, spec.flow_files.get("files")).to(cfg.device)
                show_text(bar, f"{spec.name}: errors before ({source})")
                before = flow_maps(pair, pred)
                finite_share = float(before["finite"].to(torch.float64).mean())
                # the figure of the records about to be replaced must not outlive them (with
                # --no-figures, or should the run stop before drawing it): drawn again below
                figure_path(cfg, source, spec.name).unlink(missing_ok=True)
                flows, maps, unrefined = {}, {}, set()
                for variant in cfg.variants:
                    show_text(bar, f"{spec.name}: refining {source} with odometry '{variant}'")
                    record, flow, after = _refine_one(cfg, refiners[variant], pair, pred, road,
                                                      _camera_for(variant, cam, cfg), variant, before, spec.name)
                    record.update({"pair": spec.name, "source": source, "variant": variant, "mode": cfg.mode,
                                   "road": road_from, **road_info, "prediction_finite": finite_share,
                                   "rank": rank, "fingerprint": cfg.fingerprint,
                                   "input_fingerprint": input_fp[variant]})
                    p = paths(cfg, source, variant, spec.name)
                    record["flow_png_dropped"] = _write_flow_png(p["flow"], after)
                    record["flow_digest"] = file_digest(p["flow"])
                    write_json(p["record"], record)
                    records.append({**record, "resumed": False})
                    flows[variant], maps[variant] = flow, after
                    if not record["refined"]:
                        unrefined.add(variant)
                if cfg.figures:
                    show_text(bar, f"{spec.name}: drawing the figure ({source})")
                    _figure(cfg, source, spec.name, pair, pred, road, before, flows, maps, figures, unrefined)
    finally:  # the bar ends its line before any error is printed; the figures kept open for redrawing
        bar.close()
        for figure in figures.values():
            figure.close()
    return records


def _write_flow_png(path: Path, after: dict) -> int:
    """Write the refined flow as a KITTI 16-bit PNG; return how many of its finite pixels the
    format cannot hold (beyond [-512, 511.98] px), which it marks invalid.

    The road's flow reaches that far where the car moves fast: a road point a few metres ahead
    passes under the camera and leaves the image by hundreds of pixels (a random network's flow
    does too). The job's metrics are taken before, on the flow itself; the record counts them.
    """
    from fsof_torch.io import KITTI_FLOW_MAX, KITTI_FLOW_MIN, write_kitti_flow

    # the maps hold the flow with NaN and inf replaced, and where it was finite
    flow, finite = after["flow"].cpu(), after["finite"].cpu()
    held = ((flow >= KITTI_FLOW_MIN) & (flow <= KITTI_FLOW_MAX)).all(dim=0, keepdim=True)
    write_kitti_flow(path, flow, finite & held)
    return int((finite & ~held).sum())


def _to_device(pair: dict, device: str) -> dict:
    """The pair's tensors on ``device`` (the camera moves with the refiner)."""
    if device == "cpu":
        return pair
    out = dict(pair)
    for k in ("image1", "image2", "road", "flow", "valid"):
        if isinstance(out.get(k), Tensor):
            out[k] = out[k].to(device)
    return out


def input_fingerprint(spec: PairSpec) -> str:
    """The identity of one pair's inputs (file contents, render parameters) for resuming."""
    from .resume import fingerprint

    return fingerprint({"pair": spec.name, **spec.identity()})


def clip_fingerprint(specs: list[PairSpec], *, progress: bool = True) -> str:
    """The identity of the inputs of every pair of the clip (:func:`input_fingerprint`), which the
    variants that rest on the clip's fit depend on. Each file is read once
    (:func:`refine.inputs.digests_read_once`), with a progress bar (``clip: digest``, a step a
    pair; ``progress``: shown): before the clip's fit, a long clip's frames take seconds."""
    from fsof_torch.io.progress import progress_bar

    from .inputs import digests_read_once
    from .resume import fingerprint

    with digests_read_once(), progress_bar(specs, enabled=progress, desc="clip: digest", unit="pair") as bar:
        return fingerprint({"clip": [input_fingerprint(s) for s in bar]})


def _pair_road(pair: dict, camera: Camera, cfg: JobConfig, sources: dict,
               name: str) -> tuple[Tensor, str, dict, Tensor | None]:
    """The pair's road mask, where it came from and what was recorded about it, shared by every
    flow source; and DIS's flow where it was predicted for it (the ``dis`` source's, when the run
    has one: reused, not predicted again).

    With ``--road auto`` the road is detected once per pair, started from DIS's flow: from the
    clip's fit where the job fits the clip (which detected it so), else here. Every source is then
    refined and measured on the same road, and the report's detection summary is the pair's."""
    if cfg.road_auto and cfg.clip is not None:
        road, road_info = cfg.clip.road(name)
        return road.to(cfg.device), "auto", road_info, None
    if pair.get("road") is not None and not cfg.road_auto:
        return pair["road"].to(torch.bool), "given", {}, None
    from .sources import dis_flow

    dis = sources.get("dis") or (lambda p, _file: dis_flow(p["image1"], p["image2"]))
    dis_pred = dis(pair, None).to(cfg.device)
    road, road_from, road_info = road_mask(pair, dis_pred, camera, cfg)
    return road, road_from, road_info, dis_pred if "dis" in sources else None


def road_mask(pair: dict, pred: Tensor, camera: Camera, cfg: JobConfig) -> tuple[Tensor, str, dict]:
    """The road mask, where it came from, and with ``--road auto`` the detection's flag, reason and
    coverage (recorded per pair: a flagged pair is left unrefined, never silently). The detection
    starts from ``pred`` whole: its non-finite pixels, if any, are left out by the library."""
    if pair.get("road") is not None and not cfg.road_auto:
        return pair["road"].to(torch.bool), "given", {}
    from fsof_torch import detect_road

    if cfg.road_options:  # (what the images' size and the camera allow, named as the option that gave it)
        from fsof_torch.refinement.wrapped import check_road_options

        try:
            check_road_options(cfg.road_options, (1, *pair["image1"].shape), camera, estimated=True)
        except ValueError as err:
            raise JobError(f"--road-options: {err}") from None
    with torch.no_grad():
        det = detect_road(pair["image1"][None], pair["image2"][None], camera, flow=pred[None], **cfg.road_options)
    info = {"road_flag": det.flag[0], "road_reason": det.reason[0], "road_coverage": float(det.coverage[0]),
            "road_auto_pixels": int(det.mask.sum()), "road_max_height_m": float(det.stats["max_height_m"][0])}
    return det.usable_mask[0], "auto", info


def _refine_one(cfg: JobConfig, refiner: FreespaceRefiner, pair: dict, pred: Tensor, road: Tensor,
                camera: Camera, variant: str, before: dict, name: str) -> tuple[dict, Tensor, dict]:
    odo = _odometry(variant, pair, camera, cfg, name)
    images = (pair["image1"][None], pair["image2"][None]) if variant in WITH_IMAGES else None
    out = refiner(pred[None], road[None], camera, odo, images=images)
    flow = out.flow[0].detach()
    after = flow_maps(pair, flow, reference=before)
    m_before, m_after = compare(before, after, road)
    refined = bool(out.refined[0])
    record: dict[str, Any] = {
        "road_pixels": int(road.sum()), "refined": refined,
        # a pair left unrefined used no road motion: null, not the refiner's placeholder zeros
        # (which the report's z_d error and the clip summary would take for an estimate)
        "odometry": {k: float(v[0]) if refined else None for k, v in out.odometry.items()},
        "model": out.model, "roll": float(out.camera.roll[0]), "pitch": float(out.camera.pitch[0]),
        "before": m_before, "after": m_after,
    }
    if out.gate is not None:  # what the images decided (see fsof_torch.ImageGate)
        g = out.gate
        record["gate"] = {"model_used": bool(g.model_used[0]), "confirmed": bool(g.confirmed[0]),
                          "informative": bool(g.informative[0]), "cells": int(g.cells[0]),
                          "cells_kept": int(g.cells_kept[0]), "census_model": float(g.cost_model[0]),
                          "census_prediction": float(g.cost_prediction[0])}
    if variant == "sequence":
        record["clip_fit_success"] = cfg.clip.success[name]
    if pair.get("odometry") is not None or pair.get("relative_pose") is not None:
        record["odometry_given"] = _odometry("given", pair, camera, cfg, name)
    if out.fit is not None:
        record["fit_success"] = bool(out.fit.success.all())
        extras = out.fit.extras or {}
        if "correlation" in extras:  # an image fit: its residual is photometric, and its image tests
            record["fit_residual_grey"] = float(out.fit.residual[0])
            record["fit_correlation"] = float(extras["correlation"][0])
            record["fit_inlier_share"] = float(extras["inlier_fraction"][0])
        else:
            record["fit_residual_px"] = float(out.fit.residual[0])
    return record, flow, after


def _figure(cfg: JobConfig, source: str, name: str, pair: dict, pred: Tensor, road: Tensor,
            before: dict, flows: dict[str, Tensor], maps: dict[str, dict], figures: dict[tuple, Any],
            unrefined: set[str] = frozenset()) -> None:
    """Write the pair's figure, redrawing the PairFigure of its layout in ``figures`` (built on
    first use): building a figure costs matplotlib more than redrawing it. The columns of the
    variants in ``unrefined`` (which left the pair as predicted) say so in their titles."""
    from fsof_torch.evaluation.figures import PairFigure, save_figure

    gt = pair.get("flow") is not None
    columns = {f"before ({source})": (pred, before)}
    columns.update({f"after, odometry '{v}'" + (" (left unrefined)" if v in unrefined else ""): (flows[v], maps[v])
                    for v in flows})
    cpu = lambda t: t.detach().cpu()  # noqa: E731
    panels = {k: error_panel(m) for k, (_, m) in columns.items()}
    label = next(iter(panels.values()))[2]
    content = dict(images=(cpu(pair["image1"]), cpu(pair["image2"])),
                   flows={k: cpu(f) for k, (f, _) in columns.items()},
                   errors={k: (cpu(e), cpu(v)) for k, (e, v, _) in panels.items()}, road=cpu(road))
    layout = PairFigure.layout_of(**content, error_vmax=5.0 if gt else 0.5, error_label=label)
    if layout not in figures:
        figures[layout] = PairFigure(*layout)
    fig = figures[layout].update(**content, max_flow=max_flow(pair, pred, road),
                                 title=figure_text(f"pair {name}, flow source '{source}': flow and error before "
                                                   f"and after refinement (mode '{cfg.mode}'); error: "
                                                   + ("|flow − ground truth|" if gt else
                                                      "census distance of I1 and I2 warped by the flow, 0–1")))
    save_figure(fig, figure_path(cfg, source, name), close=False)


def figure_text(text: str) -> str:
    """``text`` (a title holding a path or a frame's name) as matplotlib is to draw it, character
    for character: each ``$`` escaped, which would otherwise open mathtext, so that a folder
    ``run$1$`` was titled ``run1`` and one holding ``$$`` (or ``$5_to_$``) failed the figure, and
    with it the run after its last pair, before its report."""
    return text.replace("$", r"\$")
