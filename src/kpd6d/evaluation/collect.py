"""Multirun results: each run's metrics.json gathered into one table and plots (``kpd6d-collect``).

A Hydra multirun folder holds one sub-folder per job (``0/``, ``1/``, ...), each with
``.hydra/overrides.yaml`` (what the job changed) and ``metrics.json`` (written by
``kpd6d-evaluate``, or by ``kpd6d-train`` runs that evaluate). :func:`collect` writes:

* ``summary.md`` and ``summary.csv``: one row per run, the overrides as columns, then the mean
  metrics (and, in the CSV, every per-object metric);
* ``accuracy_vs_top_l.png`` when the runs sweep ``select.top_l`` (the paper's Fig. "number of
  selected keypoints");
* ``per_object_by_<override>.png``: a grouped bar chart of a per-object metric for each value of the
  varied override (e.g. SIFT vs bbox corners per object).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from pathlib import Path
from typing import Any

from kpd6d.io import atomic_write_text

__all__ = ["collect", "find_runs"]

MEAN_KEYS = ("mean",)  # metrics.json's aggregate node
PER_OBJECT_KEYS = ("per_object", "objects")


def _read_overrides(run: Path) -> dict[str, str]:
    f = run / ".hydra" / "overrides.yaml"
    if not f.is_file():
        return {}
    from omegaconf import OmegaConf

    out = {}
    for item in OmegaConf.to_container(OmegaConf.load(f)) or []:
        key, _, value = str(item).partition("=")
        out[key.lstrip("+~")] = value
    return out


def find_runs(root: Path) -> list[Path]:
    """The runs under ``root``, in a stable (natural) order: Hydra job folders (with ``.hydra/``) that
    hold a metrics.json; without any, every folder that holds one. A job's own sub-folders (e.g.
    ``kpd6d-run``'s ``eval/`` and ``kpd/``) are not separate runs."""
    found = {p.parent for p in Path(root).rglob("metrics.json")}
    jobs = {d for d in found if (d / ".hydra").is_dir()}
    return sorted(jobs or found, key=_natural_key)


def _natural_key(p: Path):
    return [int(s) if s.isdigit() else s for s in p.relative_to(p.anchor).parts]


def _split_metrics(metrics: dict) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    mean = next((metrics[k] for k in MEAN_KEYS if isinstance(metrics.get(k), dict)), None)
    if mean is None:  # flat file: scalars at top level
        mean = {k: v for k, v in metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    mean_scalars = {k: float(v) for k, v in mean.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    per_obj_raw = next((metrics[k] for k in PER_OBJECT_KEYS if isinstance(metrics.get(k), dict)), {})
    per_obj = {
        str(oid): {k: float(v) for k, v in vals.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
        for oid, vals in per_obj_raw.items()
        if isinstance(vals, dict)
    }
    return mean_scalars, per_obj


def collect(root: str | os.PathLike, out: str | os.PathLike | None = None) -> dict[str, Any]:
    """Collect the runs under ``root``; write summary.md/csv and plots into ``out`` (default ``root``)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"kpd6d-collect: {root} is not a folder")
    runs = find_runs(root)
    if not runs:
        raise FileNotFoundError(f"kpd6d-collect: no metrics.json under {root}; is it a finished multirun folder?")
    out = Path(out) if out else root
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for run in runs:
        try:
            metrics = json.loads((run / "metrics.json").read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"kpd6d-collect: {run / 'metrics.json'} is not valid JSON: {exc}") from exc
        mean, per_obj = _split_metrics(metrics)
        rows.append({"run": str(run.relative_to(root)) or ".", "overrides": _read_overrides(run),
                     "mean": mean, "per_object": per_obj})
    override_keys = sorted({k for r in rows for k in r["overrides"]})
    varied = [k for k in override_keys if len({r["overrides"].get(k) for r in rows}) > 1]
    mean_keys = sorted({k for r in rows for k in r["mean"]})
    obj_ids = sorted({o for r in rows for o in r["per_object"]}, key=lambda s: (len(s), s))
    obj_keys = sorted({k for r in rows for vals in r["per_object"].values() for k in vals})

    # CSV: everything
    header = ["run", *override_keys, *mean_keys, *[f"obj{o}.{k}" for o in obj_ids for k in obj_keys]]
    fh = io.StringIO()
    w = csv.writer(fh)
    w.writerow(header)
    for r in rows:
        w.writerow([r["run"], *[r["overrides"].get(k, "") for k in override_keys],
                    *[_fmt(r["mean"].get(k)) for k in mean_keys],
                    *[_fmt(r["per_object"].get(o, {}).get(k)) for o in obj_ids for k in obj_keys]])
    atomic_write_text(out / "summary.csv", fh.getvalue())

    # Markdown: overrides that vary + mean metrics
    cols = varied or override_keys
    lines = [f"# Multirun summary: {root}", "", f"{len(rows)} runs.", ""]
    lines.append("| run | " + " | ".join(cols + mean_keys) + " |")
    lines.append("|" + "---|" * (1 + len(cols) + len(mean_keys)))
    for r in rows:
        lines.append("| " + " | ".join([r["run"], *[r["overrides"].get(k, "") for k in cols],
                                          *[_fmt(r["mean"].get(k)) for k in mean_keys]]) + " |")
    plots = _plots(rows, varied, out)
    if plots:
        lines += ["", *[f"![{p.stem}]({p.name})" for p in plots]]
    atomic_write_text(out / "summary.md", "\n".join(lines) + "\n")
    return {"rows": rows, "varied": varied, "plots": [str(p) for p in plots],
            "csv": str(out / "summary.csv"), "markdown": str(out / "summary.md")}


def _fmt(v: float | None) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    return f"{v:.4f}" if abs(v) < 1e4 else f"{v:.1f}"


def _pick(keys, *cands):
    for c in cands:
        for k in keys:
            if k == c:
                return k
    for c in cands:
        for k in keys:
            if c in k:
                return k
    return None


def _plots(rows, varied, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kpd6d.evaluation.report import save_figure

    made = []
    mean_keys = sorted({k for r in rows for k in r["mean"]})
    acc_keys = [k for k in (_pick(mean_keys, "add_s_01d", "add_s_0.1d", "add_0.1d", "add"), _pick(mean_keys, "proj2d_5px", "proj2d"))
                if k]
    topl_key = next((k for k in varied if k.endswith("top_l")), None)
    if topl_key and acc_keys:
        pts = sorted(((float(r["overrides"][topl_key]), r) for r in rows if r["overrides"].get(topl_key, "").
                      replace(".", "", 1).isdigit()), key=lambda x: x[0])
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for k in acc_keys:
            ax.plot([p for p, _ in pts], [100 * r["mean"].get(k, float("nan")) for _, r in pts], "o-", label=k)
        ax.set_xlabel("number of selected keypoints (top-l)")
        ax.set_ylabel("accuracy (%)")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        made.append(save_figure(fig, out / "accuracy_vs_top_l.png", dpi=120))
    for key in varied:
        if key == topl_key:
            continue
        obj_ids = sorted({o for r in rows for o in r["per_object"]}, key=lambda s: (len(s), s))
        okeys = sorted({k for r in rows for v in r["per_object"].values() for k in v})
        metric = _pick(okeys, "add_s_01d", "add_s_0.1d", "add_0.1d", "proj2d_5px", "add", "proj2d")
        if not obj_ids or not metric:
            continue
        values = sorted({r["overrides"].get(key, "") for r in rows})
        fig, ax = plt.subplots(figsize=(max(5, 0.8 * len(obj_ids) + 2), 3.5))
        width = 0.8 / max(len(values), 1)
        for i, val in enumerate(values):
            sel = [r for r in rows if r["overrides"].get(key, "") == val]
            ys = [100 * sum(r["per_object"].get(o, {}).get(metric, float("nan")) for r in sel) / len(sel) for o in obj_ids]
            ax.bar([j + i * width for j in range(len(obj_ids))], ys, width, label=f"{key}={val}")
        ax.set_xticks([j + width * (len(values) - 1) / 2 for j in range(len(obj_ids))], [f"obj {o}" for o in obj_ids])
        ax.set_ylabel(f"{metric} (%)")
        ax.legend(fontsize=8)
        ax.grid(axis="y", alpha=0.3)
        fig.tight_layout()
        made.append(save_figure(fig, out / f"per_object_by_{key.replace('/', '_').replace('.', '_')}.png", dpi=120))
    return made
