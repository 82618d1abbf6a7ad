"""The report of a run: metrics pooled over its pairs (KITTI style: sums over all counted pixels
of the set divided by their number), per flow source and odometry variant, as Markdown and
JSON; and the per-source clip summaries.

The pooled numbers are built from a table of per-pair sums and counts (float64), which
several processes add up exactly (each pair's slot holds one process's numbers, the others add
zeros) and then reduce over the pairs in their order: the report of a distributed run equals the
single-process report.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from .job import VARIANT_HELP, JobConfig

METRICS = (("photo_road", "photometric error, road (0-255)"), ("photo_all", "photometric error, all"),
           ("photo_road_noc", "photometric error, non-occluded road (0-255)"),
           ("photo_all_noc", "photometric error, non-occluded (0-255)"),
           ("epe_road", "end-point error, road (px)"), ("epe_all", "end-point error, all (px)"))
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
        if r["variant"] in ("fit", "photometric") and "odometry_given" in r:
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
        for k, (key, _) in enumerate(METRICS):
            pooled = []
            for s in range(len(STAGES)):
                total, count = _ordered_sum(metrics[:, j, k, s, 0]), _ordered_sum(metrics[:, j, k, s, 1])
                pooled.append(total / count if count else None)
            b, a = pooled
            if b is None or a is None:
                continue
            row[f"{key}_before"] = b
            row[f"{key}_after"] = a
            row[f"{key}_change_pct"] = 100.0 * (a - b) / b if b else None
        n = _ordered_sum(extra[:, j, _ZD_N])
        if n:
            row["z_d_abs_error_m"] = _ordered_sum(extra[:, j, _ZD_ERR]) / n
        rows.append(row)
    resumed = sum(1 for r in records if r.get("resumed"))
    records = [{k: v for k, v in r.items() if k != "resumed"} for r in records]
    return {"title": cfg.title, "mode": cfg.mode, "scale_px": cfg.scale, "sources": cfg.sources,
            "variants": cfg.variants, "fit_roll": cfg.fit_roll, "fit_pitch": cfg.fit_pitch,
            "road": "auto" if cfg.road_auto else "given", "world_size": world_size,
            "fingerprint": cfg.fingerprint, "identity": identity, "rows": rows, "notes": cfg.notes,
            "records_resumed": resumed, "records_computed": len(records) - resumed, "pairs": records}


def _ordered_sum(values: torch.Tensor) -> float:
    """Sum over the pairs in their order (a Python loop: the same additions in every run)."""
    total = 0.0
    for v in values.tolist():
        total += v
    return total


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
          "Photometric error: mean |I1 − warp(I2, flow)| on the 0–255 scale over the pixels where the "
          "sample points of both the prediction and the refined flow fall inside image 2 (the same pixels "
          "before and after); with ground truth also over the non-occluded ones only ('noc': the valid "
          "ground-truth pixels, where end-point error is measured; an occluded pixel has no true match). "
          "End-point error against the ground truth (KITTI style, over all valid pixels of the set). "
          "'road' is the road mask the refiner used. 'pairs' counts refined/processed pairs.", "", table, ""]
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
    """With ``--road auto``: how many pairs' roads were flagged (left unrefined), why, and the
    coverage of the others (each pair's flag, reason and coverage are in report.json)."""
    found = {r["pair"]: r for r in summary["pairs"] if "road_flag" in r}
    if not found:
        return []
    ok = [r["road_coverage"] for r in found.values() if r["road_flag"] == "ok"]
    flagged = {p: f'{r["road_flag"]} ({r["road_reason"]})' for p, r in found.items() if r["road_flag"] != "ok"}
    line = (f"- Auto road (found in the images): {len(found) - len(flagged)} of {len(found)} pairs ok"
            + (f", covering {100 * sum(ok) / len(ok):.1f} % (min {100 * min(ok):.1f} %) of the image below the "
               f"horizon" if ok else ""))
    return [line] + [f"  - flagged, left unrefined: {p}: {why}" for p, why in sorted(flagged.items())]


def write_clip_summaries(summary: dict, cfg: JobConfig) -> list[Path]:
    """``OUT/<source>/summary.png`` per flow source: error before and after, and every estimated
    motion and mounting field of the records, over the pairs."""
    from fsof_torch.evaluation.figures import clip_summary_figure, save_figure

    written = []
    for source in cfg.sources:
        records = [r for r in summary["pairs"] if r["source"] == source]
        if not records:
            continue
        gt = any("epe_road" in r["before"] for r in records)
        key, label = ("epe_road", "end-point error, road (px)") if gt else \
            ("photo_road", "photometric error, road (grey levels)")
        fig = clip_summary_figure(records, error_key=key, error_label=label,
                                  title=f"{cfg.title}: flow source '{source}' over the pairs")
        path = cfg.out / source / "summary.png"
        save_figure(fig, path)
        written.append(path)
    return written
