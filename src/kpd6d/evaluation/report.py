"""Evaluation reports: ``report.md`` (paper-style per-object table), accuracy-threshold plots and
3D-box overlays (ground truth green, prediction blue), from a ``metrics.json`` dict written by
:func:`kpd6d.evaluation.runner.evaluate`."""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from kpd6d.io import atomic_write_bytes, atomic_write_text

__all__ = ["plot_curves", "save_figure", "write_report_md"]

# ---------------------------------------------------------------------------------------------
# plots
# ---------------------------------------------------------------------------------------------
def plot_curves(metrics: dict, out_dir: str | os.PathLike) -> list[Path]:
    """``accuracy_vs_px.png`` (2D projection) and ``accuracy_vs_add.png`` (ADD(-S)), per object + mean."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir = Path(out_dir)
    paths = []
    curves = metrics["curves"]
    for key, xlabel, fname, title in (
        ("proj2d", "pixel threshold", "accuracy_vs_px.png", "2D projection accuracy"),
        ("add_s", "ADD(-S) threshold (fraction of diameter)", "accuracy_vs_add.png", "ADD(-S) accuracy"),
    ):
        th = np.asarray(curves[f"{key}_thresholds"])
        fig, ax = plt.subplots(figsize=(6, 4.5), dpi=100)
        for oid, obj in sorted(metrics["per_object"].items(), key=lambda kv: int(kv[0])):
            ax.plot(th, 100 * np.asarray(obj["curves"][key]), lw=1.2, label=f"{obj.get('name') or 'obj'} ({oid})")
        ax.plot(th, 100 * np.asarray(metrics["mean"]["curves"][key]), "k--", lw=2.2, label="mean")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("accuracy (%)")
        ax.set_ylim(0, 100)
        ax.set_xlim(th[0], th[-1])
        ax.grid(alpha=0.3)
        ax.set_title(title)
        ax.legend(fontsize=7, ncol=2, loc="lower right")
        fig.tight_layout()
        paths.append(save_figure(fig, out_dir / fname))
    return paths


def save_figure(fig, path: str | os.PathLike, dpi: int = 100) -> Path:
    """Save a matplotlib figure as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


# ---------------------------------------------------------------------------------------------
# report.md
# ---------------------------------------------------------------------------------------------
def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.1f}"


def write_report_md(metrics: dict, path: str | os.PathLike, overlays: list[str] | None = None) -> Path:
    """Paper-style per-object table (ADD(-S) 0.1d, 2D proj. 5 px, AR_MSSD, AR_MSPD) and the run's settings."""
    path = Path(path)
    lines = ["# kpd6d evaluation", ""]
    info = metrics.get("run", {})
    for k in ("dataset", "split", "targets", "detector", "kpd", "pnp", "top_l", "refine_boxes", "box_scale", "crop_tta",
              "depth_calibration", "refiner", "frames", "device"):
        if k in info:
            lines.append(f"- {k}: `{info[k]}`")
    lines += ["", "| object | id | n | ADD(-S) 0.1d (%) | 2D proj. 5 px (%) | 10 px (%) | 15 px (%) | AUC ADD(-S) ≤0.5d (%) "
              "| AR_MSSD (%) | AR_MSPD (%) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for oid, o in sorted(metrics["per_object"].items(), key=lambda kv: int(kv[0])):
        sym = " *" if o.get("symmetric") else ""
        lines.append(f"| {o.get('name') or '-'}{sym} | {oid} | {o['n']} | {_pct(o['add_s_01d'])} | {_pct(o['proj2d_5px'])} | "
                     f"{_pct(o.get('proj2d_10px'))} | {_pct(o.get('proj2d_15px'))} | "
                     f"{_pct(o['auc_add_s'])} | {_pct(o.get('ar_mssd'))} | {_pct(o.get('ar_mspd'))} |")
    m = metrics["mean"]
    lines.append(f"| **mean** | | {m['n']} | **{_pct(m['add_s_01d'])}** | **{_pct(m['proj2d_5px'])}** | "
                 f"{_pct(m.get('proj2d_10px'))} | {_pct(m.get('proj2d_15px'))} | "
                 f"{_pct(m['auc_add_s'])} | {_pct(m.get('ar_mssd'))} | {_pct(m.get('ar_mspd'))} |")
    lines += ["", "`*` symmetric object: ADD-S instead of ADD, 2D projection error minimised over its symmetries. Mean = mean over objects. Objects not detected or "
              "with a failed PnP count as failures.", ""]
    bop = metrics.get("bop19") or {}
    if bop:
        lines.append(f"BOP19 (results.csv scored by kpd6d-score): AR_MSSD {_pct(bop.get('ar_mssd'))} %, "
                     f"AR_MSPD {_pct(bop.get('ar_mspd'))} %. VSD: {bop.get('vsd', 'skipped')}.")
    dec = bop.get("decomposition")
    if dec:
        from kpd6d.evaluation.decompose import LABELS

        lines += ["", "Where the score is lost (a diagnosis: the same estimates scored again with one part of each "
                  "pose taken from the nearest GT instance; kpd6d.evaluation.decompose):", "",
                  "| poses | AR_MSSD (%) | AR_MSPD (%) |", "|---|---:|---:|"]
        lines += [f"| {LABELS.get(k, k)} | {_pct(v['ar_mssd'])} | {_pct(v['ar_mspd'])} |" for k, v in dec.items()]
        lines.append("")
    fps = metrics.get("fps")
    if fps:
        lines.append(f"Speed: {fps:.2f} frames/s end to end on {info.get('device', '?')} "
                     f"(batch size {info.get('batch_size', '?')}); stage times per frame (ms): "
                     + ", ".join(f"{k} {1000 * v:.1f}" for k, v in metrics.get("stage_seconds_per_frame", {}).items()))
    lines.append(f"Failures (not detected or PnP not ok): {metrics.get('failures', 0)} of {m['n']} instances.")
    kp_objs = [(oid, o) for oid, o in sorted(metrics["per_object"].items(), key=lambda kv: int(kv[0])) if "keypoints" in o]
    if kp_objs:
        lines += ["", "Keypoints against the ground truth (the KPD's 2D keypoints of each matched instance, the ones its "
                  "pose came from, against its 3D keypoints projected at the GT pose; medians over the instances): "
                  "error = median distance, centroid = offset of their centroid, scale = size of the predicted pattern "
                  "about its centroid relative to the GT's (< 1: drawn in, which PnP turns into too large a depth).",
                  "", "| object | id | n | error (px) | centroid (px) | scale |", "|---|---:|---:|---:|---:|---:|"]
        rows = [(o.get("name") or "-", oid, o["keypoints"]) for oid, o in kp_objs]
        rows += [("**mean**", "", m["keypoints"])] if m.get("keypoints") else []
        lines += [f"| {name} | {oid} | {k['n']} | {k['err_px']:.1f} | {k['centroid_px']:.1f} | {k['scale']:.3f} |"
                  for name, oid, k in rows]
    dv = [b for b in metrics.get("depth_by_visibility") or [] if b["n"]]
    if dv:
        lines += ["", "Depth by visibility (estimated / true depth of each matched object's centre, by the share of "
                  "the object visible; > 1: too far): median (IQR) and the share within 2 % of the truth.", "",
                  "| visible fraction | n | depth ratio | within 2 % |", "|---|---:|---:|---:|"]
        lines += [f"| {b['lo']:.2f}–{b['hi']:.2f} | {b['n']} | {b['median']:.3f} ({b['q25']:.3f}–{b['q75']:.3f}) | "
                  f"{_pct(b['within'])} % |" for b in dv]
    det = metrics.get("detector")
    if det:
        names = {oid: o.get("name") or "-" for oid, o in metrics["per_object"].items()}
        lines += ["", f"Detector on the same frames ({det.get('images', '?')} images, {det.get('num_gt', '?')} objects): "
                  f"AP@0.5 {_pct(det.get('map_50'))} %, AP@0.5:0.95 {_pct(det.get('map'))} %, recall@IoU 0.5 "
                  f"{_pct(det.get('recall_at_iou'))} %.", "", "| object | id | AP@0.5 (%) |", "|---|---:|---:|"]
        for oid, ap in sorted((det.get("ap50_per_object") or {}).items(), key=lambda kv: int(kv[0])):
            lines.append(f"| {names.get(str(oid), '-')} | {oid} | {_pct(ap)} |")
    lines += ["", "![accuracy vs pixel threshold](accuracy_vs_px.png)", "",
              "![accuracy vs ADD threshold](accuracy_vs_add.png)", ""]
    for ov in overlays or []:
        lines.append(f"![overlay]({ov})")
    if overlays:
        lines += ["", "Overlays: ground truth green, prediction blue."]
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
