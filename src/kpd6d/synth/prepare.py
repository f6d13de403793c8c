"""The one data-preparation path: the splits of a synthetic dataset, generated resumably into one
root (:func:`generate_splits`), and the dataset a training stage reads (:func:`prepare_data`: a given
``data.root``, or the splits generated into ``<run dir>/data`` from the stage's ``generate`` node).
The workflow (``kpd6d-run``), both training stages (``kpd6d-train``) and ``kpd6d-generate`` all
write data through :func:`kpd6d.synth.generate_dataset` by way of these two functions.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from kpd6d.io import to_plain

__all__ = ["generate_splits", "prepare_data"]


def generate_splits(root: str | Path, splits: Sequence[tuple[str, int, int]], *, models_dir: str | None = None,
                    obj_ids: Sequence[int] | None = None, workers: int = 0, progress: bool = False,
                    options: Mapping[str, Any] | None = None, log: Callable[[str], None] | None = None) -> Path:
    """Write each ``(split, num_images, seed)`` of ``splits`` into ``root`` (splits with no images or
    no name are skipped; a rerun resumes each split where it stopped). Returns ``root``."""
    from kpd6d.synth.generate import generate_dataset

    root = Path(root)
    opts = dict(to_plain(options) or {})
    with _exclusive(root.parent / f".{root.name}.generate.lock"):  # beside the dataset, not in it
        for split, n, seed in splits:
            if not split or not n:
                continue
            if log is not None:
                log(f"generating {int(n)} {split} images into {root}")
            generate_dataset(root, models_dir=models_dir, obj_ids=to_plain(obj_ids), num_images=int(n), split=split,
                             seed=int(seed), workers=int(workers), progress=progress, **opts)
    return root


@contextlib.contextmanager
def _exclusive(lock_path: Path):
    """One process at a time generates into a root (the others wait, then find it complete): the
    processes of a DDP run all prepare the same data. An advisory ``flock``, released when its holder
    exits or dies, so a crashed process never leaves the others waiting (local file systems; on a
    shared one, generate first: ``kpd6d-generate``, then ``data.root=``)."""
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_path, "a") as fh:
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX: no lock
            yield
            return
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def prepare_data(data_root: str | None, run_dir: str | Path, generate: Mapping[str, Any],
                 splits: Sequence[str | None]) -> Path:
    """``data_root`` when given (it must exist), else the ``splits`` (train first, then val) generated
    into ``<run_dir>/data`` from a ``generate`` node (kpd6d-train's ``data.generate``: ``obj_ids``,
    ``num_train``, ``num_val``, ``seed`` (split i gets ``seed + 1000 i``), ``workers`` and optional
    ``options``)."""
    if data_root:
        root = Path(data_root)
        if not root.is_dir():
            raise FileNotFoundError(f"data.root {str(root)!r} does not exist (set data.root=null to generate one)")
        return root
    if not generate:
        raise ValueError("data.root is null and there is no data.generate node to generate a dataset from: "
                         "set data.root=<BOP dataset> or give data.generate (conf/train.yaml)")
    g = generate
    counts = (g["num_train"], g["num_val"])
    seed = int(g["seed"])
    return generate_splits(Path(run_dir) / "data",
                           [(s, n, seed + 1000 * i) for i, (s, n) in enumerate(zip(splits, counts))],
                           obj_ids=g.get("obj_ids"), workers=int(g["workers"]), options=g.get("options"))
