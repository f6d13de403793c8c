"""BOP challenge results CSV: the one place that reads and writes it.

Format (BOP 2019+): a header line ``scene_id,im_id,obj_id,score,R,t,time`` and one line per pose
estimate; ``R`` is 9 space-separated values (row-major), ``t`` 3 space-separated values in mm,
``time`` the wall time in seconds spent on the whole image (the same for all estimates of an
image; -1 when unknown).
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kpd6d.geometry import rotation_problem
from kpd6d.io import atomic_write_text

__all__ = ["HEADER", "PoseResult", "ResultsFormatError", "read_bop_results", "write_bop_results"]

HEADER = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")


class ResultsFormatError(ValueError):
    """A results CSV that cannot be read; the message names the file, line and field."""


@dataclass
class PoseResult:
    """One pose estimate of a BOP results file (R (3, 3), t (3,) in mm, model -> camera)."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    time: float = -1.0


def _parse_floats(text: str, n: int, path: Path, line: int, field: str) -> np.ndarray:
    parts = text.split()
    if len(parts) != n:
        raise ResultsFormatError(f"{path}:{line}: field {field!r} has {len(parts)} values, expected {n}: {text!r}")
    try:
        vals = np.array([float(p) for p in parts], dtype=np.float64)
    except ValueError:
        raise ResultsFormatError(f"{path}:{line}: field {field!r} is not numeric: {text!r}") from None
    if not np.isfinite(vals).all():
        raise ResultsFormatError(f"{path}:{line}: field {field!r} has non-finite values: {text!r}")
    return vals


def read_bop_results(path: str | os.PathLike) -> list[PoseResult]:
    """Read a BOP results CSV (the ``time`` column may be missing: it then reads as -1)."""
    path = Path(path)
    if not path.is_file():
        raise ResultsFormatError(f"{path}: results file does not exist")
    text = path.read_text()
    rows = list(csv.reader(io.StringIO(text)))
    if not rows:
        raise ResultsFormatError(f"{path}: results file is empty; expected the header {','.join(HEADER)}")
    header = tuple(h.strip() for h in rows[0])
    if header not in (HEADER, HEADER[:-1]):
        raise ResultsFormatError(
            f"{path}:1: unexpected header {','.join(header)!r}; expected {','.join(HEADER)!r}"
        )
    has_time = len(header) == len(HEADER)
    out: list[PoseResult] = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise ResultsFormatError(f"{path}:{lineno}: {len(row)} fields, expected {len(header)} ({','.join(header)})")
        vals = {}
        for name in ("scene_id", "im_id", "obj_id"):
            try:
                vals[name] = int(row[header.index(name)])
            except ValueError:
                raise ResultsFormatError(f"{path}:{lineno}: field {name!r} is not an integer: {row[header.index(name)]!r}") from None
        try:
            score = float(row[3])
        except ValueError:
            raise ResultsFormatError(f"{path}:{lineno}: field 'score' is not a number: {row[3]!r}") from None
        if not math.isfinite(score):
            raise ResultsFormatError(f"{path}:{lineno}: field 'score' is not finite: {row[3]!r}")
        R = _parse_floats(row[4], 9, path, lineno, "R").reshape(3, 3)
        why = rotation_problem(R)
        if why:
            raise ResultsFormatError(f"{path}:{lineno}: field 'R' {why}: {row[4]!r}")
        t = _parse_floats(row[5], 3, path, lineno, "t")
        tm = -1.0
        if has_time:
            try:
                tm = float(row[6])
            except ValueError:
                raise ResultsFormatError(f"{path}:{lineno}: field 'time' is not a number: {row[6]!r}") from None
        out.append(PoseResult(vals["scene_id"], vals["im_id"], vals["obj_id"], score, R, t, tm))
    return out


def _fmt(values: Iterable[float]) -> str:
    return " ".join(repr(float(v)) for v in values)


def write_bop_results(path: str | os.PathLike, results: Iterable[PoseResult]) -> Path:
    """Write ``results`` as a BOP results CSV atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [",".join(HEADER)]
    for r in results:
        R = np.asarray(r.R, dtype=np.float64).reshape(-1)
        t = np.asarray(r.t, dtype=np.float64).reshape(-1)
        if R.size != 9 or t.size != 3:
            raise ValueError(f"{path}: result for scene {r.scene_id} image {r.im_id} obj {r.obj_id} has R with "
                             f"{R.size} values and t with {t.size}; expected 9 and 3")
        lines.append(f"{int(r.scene_id)},{int(r.im_id)},{int(r.obj_id)},{float(r.score)!r},{_fmt(R)},{_fmt(t)},{float(r.time)!r}")
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
