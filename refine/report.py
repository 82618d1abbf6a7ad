"""The report of a run: metrics pooled over its pairs (KITTI style: sums over all counted pixels
of the set divided by their number), per flow source and odometry variant, as Markdown and
JSON; and the per-source clip summaries.

The pooled numbers are built from a table of per-pair sums and counts (float64), which
several processes add up exactly (each pair's slot holds one process's numbers, the others add
zeros) and then reduce over the pairs in their order: the report of a distributed run equals the
single-process report.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import torch

from .job import VARIANT_HELP, JobConfig, figure_text
from .measure import PHOTO
from .resume import SUMMARY

# (record key, label): each photometric kind inside the road and overall, and over the
# non-occluded pixels where ground truth exists; end-point error where ground truth exists
METRICS = tuple((f"{prefix}_{region}", f"{label}, {where}")
                for prefix, _, label in PHOTO
                for region, where in (("road", "road"), ("all", "all"), ("road_noc", "non-occluded road"),
                                      ("all_noc", "non-occluded"))) + \
    (("epe_road", "end-point error (px), road"), ("epe_all", "end-point error (px), all"))
STAGES = ("before", "after")
# extra per-pair columns: refined (0/1), processed (1), |z_d − given z_d| (m) with its count
_REFINED, _PROCESSED, _ZD_ERR, _ZD_N = range(4)


def pair_table(records: list[dict], names: list[str], cfg: JobConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pair sums and counts of this process's records.

    Returns ``(metrics, extra)``: ``metrics`` (pairs, sources·variants, metrics, 2 stages, 2) holds
    (mean × count, count) per stage; ``extra`` (pairs, sources·variants, 4) holds refined,
    processed, |z_d error| and its count. Pairs of other processes are zero.
    """
    row = {n: i for i, n in enumerate(names)}
    col = {(s, v): j for j, (s, v) in enumerate((s, v) for s in cfg.sources for v in cfg.variants)}
    metrics = torch.zeros(len(names), len(col), len(METRICS), len(STAGES), 2, dtype=torch.float64)
    extra = torch.zeros(len(names), len(col), 4, dtype=torch.float64)
    for r in records:
        i, j = row[r["pair"]], col[(r["source"], r["variant"])]
        for k, (key, _) in enumerate(METRICS):
            for s, stage in enumerate(STAGES):
                m = r[stage]
                n = m.get(f"{key}_n", 0) if key in m else 0
                if n:
                    metrics[i, j, k, s, 0] = m[key] * n
                    metrics[i, j, k, s, 1] = n
        extra[i, j, _REFINED] = float(r["refined"])
        extra[i, j, _PROCESSED] = 1.0
        # the variants that estimate the motion (given_images where --odometry-sigma lets the images move it)
        estimated = r["variant"] in ("fit", "photometric", "sequence") or (
            r["variant"] == "given_images" and cfg.odometry_sigma is not None)
        if estimated and "odometry_given" in r and r["refined"] \
                and isinstance(r["odometry"].get("z_d"), (int, float)):  # (no motion where left unrefined)
            extra[i, j, _ZD_ERR] = abs(r["odometry"]["z_d"] - r["odometry_given"]["z_d"])
            extra[i, j, _ZD_N] = 1.0
    return metrics, extra


def summarize(metrics: torch.Tensor, extra: torch.Tensor, records: list[dict], cfg: JobConfig, *,
              world_size: int = 1, identity: dict | None = None) -> dict:
    """The report's content from the (all-reduced) pair table and every record of the run."""
    rows = []
    for j, (source, variant) in enumerate((s, v) for s in cfg.sources for v in cfg.variants):
        processed = int(extra[:, j, _PROCESSED].sum())
        if not processed:
            continue
        row: dict[str, Any] = {"source": source, "variant": variant, "pairs": processed,
                               "refined": int(extra[:, j, _REFINED].sum())}
        # the metrics the records hold (ground-truth ones only with ground truth), measured or not
        held = {k for r in records if (r["source"], r["variant"]) == (source, variant) for k in r["before"]}
        for k, (key, _) in enumerate(METRICS):
            pooled = []
            for s in range(len(STAGES)):
                total, count = _ordered_sum(metrics[:, j, k, s, 0]), _ordered_sum(metrics[:, j, k, s, 1])
                pooled.append(total / count if count else None)
            b, a = pooled
            if (b is None or a is None) and key not in held:
                continue
            # None (printed '–'): no pixel of any pair was measurable, e.g. the source's flow was NaN
            row[f"{key}_before"] = b
            row[f"{key}_after"] = a
            row[f"{key}_change_pct"] = 100.0 * (a - b) / b if a is not None and b else None
        n = _ordered_sum(extra[:, j, _ZD_N])
        if n:
            row["z_d_abs_error_m"] = _ordered_sum(extra[:, j, _ZD_ERR]) / n
        rows.append(row)
    resumed = sum(1 for r in records if r.get("resumed"))
    records = [{k: v for k, v in r.items() if k != "resumed"} for r in records]
    return {"title": cfg.title, "mode": cfg.mode, "scale_px": cfg.scale, "sources": cfg.sources,
            "variants": cfg.variants, "fit_roll": cfg.fit_roll, "fit_pitch": cfg.fit_pitch,
            "road": "auto" if cfg.road_auto else "given", "world_size": world_size,
            "fingerprint": cfg.fingerprint, "identity": identity, "rows": rows,
            "notes": cfg.notes + unmeasured_notes(rows, records, cfg.sources),
            "records_resumed": resumed, "records_computed": len(records) - resumed, "pairs": records}


def unmeasured_notes(rows: list[dict], records: list[dict], sources: list[str]) -> list[str]:
    """Warnings for the report: each flow source whose flow was NaN or inf at every pixel of a pair
    (nothing of that pair could be measured or refined), the pairs whose given road mask is empty,
    and what a '–' or an 'n/a' in the table means."""
    notes = []
    for source in sources:
        pairs = sorted({r["pair"] for r in records if r["source"] == source and r.get("prediction_finite") == 0.0})
        if pairs:
            total = len({r["pair"] for r in records if r["source"] == source})
            shown = ", ".join(pairs[:8]) + (", ..." if len(pairs) > 8 else "")
            notes.append(f"Warning: flow source '{source}' gave no finite flow (NaN or inf at every pixel) on "
                         f"{len(pairs)} of {total} pair(s) ({shown}): no metric could be measured there.")
    empty = sorted({r["pair"] for r in records if r.get("road") == "given" and r.get("road_pixels") == 0})
    if empty:  # (a given road with no pixel on any pair stops the job first: refine.inputs)
        total = len({r["pair"] for r in records})
        shown = ", ".join(empty[:8]) + (", ..." if len(empty) > 8 else "")
        notes.append(f"Warning: road mask empty: {shown} ({len(empty)} of {total} pair(s)): left unrefined, "
                     f"nothing measured inside the road there.")
    notes += unrefined_notes(records)
    if any(k.endswith("_before") and v is None for r in rows for k, v in r.items()):
        notes.append("'–': measured over no pixel (none where both the prediction and the refined flow are "
                     "finite and defined, inside the road mask for a road column; e.g. the source gave no "
                     "finite flow, or the road mask was empty).")
    if any(_no_relative_change(v, r.get(f"{k[:-len('_before')]}_after"))
           for r in rows for k, v in r.items() if k.endswith("_before")):
        notes.append("'n/a' in a Δ% column: the error before refinement is 0 (e.g. a source that is the ground "
                     "truth itself), so there is no relative change (`null` in report.json); compare the "
                     "values.")
    return notes


def unrefined_notes(records: list[dict]) -> list[str]:
    """One note per flow source and variant that left pairs unrefined for a reason the other notes
    do not give (a flagged auto road, an empty road mask, a flow with no finite pixel): how many,
    why (a failed fit, the clip's fit, the images' gate keeping the prediction) and which pairs."""
    unexplained: dict[tuple[str, str], dict[str, list[str]]] = {}
    for r in records:
        if r["refined"] or (r.get("road_pixels") == 0 and r.get("road") == "given") \
                or r.get("prediction_finite") == 0.0 or r.get("road_flag", "ok") != "ok":
            continue
        why = unexplained.setdefault((r["source"], r["variant"]), {})
        why.setdefault(_unrefined_reason(r), []).append(r["pair"])
    notes = []
    for (source, variant), why in unexplained.items():
        total = sum(1 for r in records if (r["source"], r["variant"]) == (source, variant))
        count = sum(len(pairs) for pairs in why.values())
        shown = "; ".join(f"{reason}: " + ", ".join(pairs[:8]) + (", ..." if len(pairs) > 8 else "")
                          for reason, pairs in why.items())
        notes.append(f"Left unrefined (the prediction kept): {source} / {variant}: {count} of {total} pair(s): "
                     f"{shown} (the records hold each fit's residual and the gate's decision).")
    return notes


def _unrefined_reason(r: dict) -> str:
    if r.get("road_pixels") == 0:  # (an auto road found but empty; a given one has its own note)
        return "the road mask is empty"
    if r.get("clip_fit_success") is False:
        return "the clip's fit failed for the pair"
    if r.get("fit_success") is False:
        return "the ego-motion fit to the flow failed" if "fit_residual_px" in r else \
            "the road motion from the images failed"
    if r.get("variant") in ("fit", "photometric") and "fit_success" not in r:
        # (these variants estimate the motion, and nothing was estimated: fewer finite predicted road
        # pixels than the refiner's min_pixels; the gate, handed none of them, judged nothing)
        return "too few usable road pixels to fit"
    gate = r.get("gate")
    if isinstance(gate, dict) and not gate.get("model_used", True):
        return "the images' gate kept the prediction"
    return "too few usable road pixels to fit, or the road model defined on none of them"


def _no_relative_change(before: Any, after: Any) -> bool:
    """A metric measured (not None) whose before is 0: no percentage of 0 (``change_pct`` None),
    printed 'n/a', not the '–' of a metric measured over no pixel."""
    return before == 0 and after is not None


def _ordered_sum(values: torch.Tensor) -> float:
    """Sum over the pairs in their order (a Python loop: the same additions in every run)."""
    total = 0.0
    for v in values.tolist():
        total += v
    return total


def _fmt_change(pct: Any) -> str:
    """A Δ% cell, one decimal: a change that rounds to zero prints 0.0, never -0.0."""
    text = _fmt(pct, 1)
    return "0.0" if text == "-0.0" else text


def _fmt(x: Any, digits: int = 3) -> str:
    if x is None:
        return "–"
    if isinstance(x, float):
        return f"{x:.{digits}f}" if math.isfinite(x) else str(x)
    return str(x)


# the report's rows per (source, variant): (record key prefix, label, digits); 'noc' rows and
# end-point error only where ground truth exists
_TABLE = tuple((prefix, label, 3 if prefix == "photo" else 4) for prefix, _, label in PHOTO) + \
    (("epe", "end-point error (px)", 3),)


def table_markdown(summary: dict) -> str:
    """One row per source, variant and metric: road and overall, before, after and change."""
    head = ["source", "odometry", "pairs", "metric", "road before", "after", "Δ%", "all before", "after", "Δ%"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in summary["rows"]:
        first = True
        for prefix, label, digits in _TABLE:
            for suffix, name in (("", label), ("_noc", f"{label}, non-occluded")):
                road, every = f"{prefix}_road{suffix}", f"{prefix}_all{suffix}"
                if f"{road}_before" not in r and f"{every}_before" not in r:
                    continue
                cells = [r["source"], r["variant"], f'{r["refined"]}/{r["pairs"]}'] if first else ["", "", ""]
                first = False
                cells.append(name)
                for key in (road, every):
                    before, after = r.get(f"{key}_before"), r.get(f"{key}_after")
                    change = "n/a" if _no_relative_change(before, after) else _fmt_change(r.get(f"{key}_change_pct"))
                    cells += [_fmt(before, digits), _fmt(after, digits), change]
                lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(summary: dict, cfg: JobConfig, json_path: Path | None) -> str:
    """``OUT/report.md``, ``OUT/report.json`` (and ``--json``); returns the Markdown table."""
    from fsof_torch.io import write_json, write_text

    table = table_markdown(summary)
    n_pairs = len({r["pair"] for r in summary["pairs"]})
    md = [f"# {summary['title']}", "",
          f"Run `{summary['fingerprint']}`: {n_pairs} pair(s); flow sources {', '.join(cfg.sources)}; "
          f"odometry {', '.join(cfg.variants)}; fusion mode `{summary['mode']}`"
          + (f" (Cauchy scale {cfg.scale:g} px)" if cfg.mode == "confidence" else "")
          + f"; road mask {summary['road']}"
          + ("; fitted roll" if cfg.fit_roll else "") + ("; fitted pitch" if cfg.fit_pitch else "")
          + f"; {summary['world_size']} process(es). "
          + (f"{summary['records_resumed']} of {len(summary['pairs'])} records were finished by an earlier "
             f"run with the same fingerprint (same inputs and options) and reused."
             if summary["records_resumed"] else "All records were computed by this run."), "",
          "Photometric error of image 1 against image 2 warped back by the flow, three kinds: the census "
          "distance (7×7 census bits of the grey images that differ, / 48), the SSIM dissimilarity "
          "((1 − SSIM) / 2) and L1 (mean |I1 − warp(I2, flow)|, 0–255); lower is better. Judge by census "
          "(and by end-point error where there is ground truth): L1 on raw intensities charges a correct "
          "flow for every exposure change between the frames and rewards a flow bent to match brightness. "
          "Each kind is averaged over the pixels where both the prediction and the refined flow are defined "
          "(sample point, and for census and SSIM its window, inside image 2: the same pixels before and "
          "after); with ground truth also over the non-occluded ones only (its valid pixels, where "
          "end-point error is measured; an occluded pixel has no true match). End-point error against the "
          "ground truth (KITTI style, over all valid pixels of the set). 'road' is the road mask the refiner "
          "used; 'all' the whole image. 'pairs' counts refined/processed pairs.", "", table, ""]
    md += [f"- {n}" for n in summary["notes"]] + auto_road_lines(summary)
    md += ["", "Odometry variants: " + "; ".join(f"`{k}`: {v}" for k, v in VARIANT_HELP.items()), ""]
    write_text(cfg.out / "report.md", "\n".join(md))
    write_json(cfg.out / "report.json", summary)
    if json_path is not None:
        if json_path.parent != Path(""):
            json_path.parent.mkdir(parents=True, exist_ok=True)
        write_json(json_path, summary)
    return table


def auto_road_lines(summary: dict) -> list[str]:
    """With ``--road auto``: how many pairs' roads were flagged (left unrefined), why (the
    detection's reason, its advice in the job's options: :func:`job_advice`), the coverage of the
    others and the steps their evidence could show (each pair's flag, reason, coverage and step
    are in report.json)."""
    found = {r["pair"]: r for r in summary["pairs"] if "road_flag" in r}
    if not found:
        return []
    ok = [r["road_coverage"] for r in found.values() if r["road_flag"] == "ok"]
    flagged = {p: f'{r["road_flag"]} ({r["road_reason"]})' for p, r in found.items() if r["road_flag"] != "ok"}
    line = (f"- Auto road (found in the images): {len(found) - len(flagged)} of {len(found)} pairs ok"
            + (f", covering {100 * sum(ok) / len(ok):.1f} % (min {100 * min(ok):.1f} %) of the image below the "
               f"horizon" if ok else ""))
    # the step the evidence had to show, larger where the vehicle drove slowly (of the pairs ok: a
    # flagged pair's is no step its evidence showed, e.g. the largest tried of a static pair)
    steps = [r["road_max_height_m"] for r in found.values() if "road_max_height_m" in r and r["road_flag"] == "ok"]
    if steps:
        line += "; the step the evidence could show: " + ", ".join(
            f"{h:g} m ({steps.count(h)} pair{'s' if steps.count(h) != 1 else ''})" for h in sorted(set(steps)))
    options = (summary.get("identity") or {}).get("road_options")  # (--road-options, where given)
    return [line] + [f"  - flagged, left unrefined: {p}: {job_advice(why, options)}"
                     for p, why in sorted(flagged.items())]


#: detect_road's advice, in a flagged road's reason, that a job user follows through --road-options
_DEEPER_SEED = "a deeper seed_depth_m"


def job_advice(reason: str, road_options: dict | None) -> str:
    """A flagged auto road's reason (``detect_road``'s, in the terms of its keyword arguments) as
    the job's user acts on it: its advice of a deeper ``seed_depth_m`` as the ``--road-options``
    that gives one, twice the depth used and at least twice the default (the run's other road
    options, ``road_options`` as given, kept beside it). The records keep the library's reason."""
    if _DEEPER_SEED not in reason:
        return reason
    import inspect

    from fsof_torch import detect_road

    default = inspect.signature(detect_road).parameters["seed_depth_m"].default
    options = dict(road_options or {})
    deeper = 2 * max(options.get("seed_depth_m", default), default)
    options["seed_depth_m"] = int(deeper) if float(deeper).is_integer() else deeper
    return reason.replace(_DEEPER_SEED, f"a deeper seed: --road-options '{json.dumps(options)}'")


def write_clip_summaries(summary: dict, cfg: JobConfig) -> list[Path]:
    """``OUT/<source>/summary.png`` per flow source: the road's errors before and after (end-point
    error where there is ground truth; census, SSIM and L1), and every estimated motion and
    mounting field of the records, over the pairs."""
    from fsof_torch.evaluation.figures import clip_summary_figure, save_figure

    written = []
    nan = lambda m: {k: float("nan") if v is None else v for k, v in m.items()}  # noqa: E731  (unmeasured)
    for source in cfg.sources:
        # (the pairs name the x axis: as their names are, see figure_text)
        records = [{**r, "pair": figure_text(r["pair"]), "before": nan(r["before"]), "after": nan(r["after"])}
                   for r in summary["pairs"] if r["source"] == source]
        if not records:
            continue
        errors = {f"{prefix}_road": f"{label}, road" for prefix, _, label in PHOTO}
        if any("epe_road" in r["before"] for r in records):
            errors = {"epe_road": "end-point error (px), road", **errors}
        fig = clip_summary_figure(records, errors=errors,
                                  title=figure_text(f"{cfg.title}: flow source '{source}' over the pairs"))
        path = cfg.out / source / SUMMARY
        save_figure(fig, path)
        written.append(path)
    return written
