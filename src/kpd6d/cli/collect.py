"""``kpd6d-collect MULTIRUN_DIR [--out DIR]``: gather each run's metrics.json into one table and plots.

Runs :func:`kpd6d.evaluation.collect.collect`: ``summary.md`` and ``summary.csv`` (one row per run,
its overrides and metrics), ``accuracy_vs_top_l.png`` when the runs sweep ``select.top_l`` and
``per_object_by_<override>.png`` for each other varied override.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from kpd6d.evaluation.collect import collect, find_runs  # find_runs: re-exported (old import path)

__all__ = ["collect", "find_runs", "main"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="kpd6d-collect", description=__doc__.split("\n\n")[0])
    ap.add_argument("multirun_dir")
    ap.add_argument("--out", default=None, help="output folder (default: the multirun folder)")
    args = ap.parse_args(argv)
    try:
        res = collect(args.multirun_dir, args.out)
    except (FileNotFoundError, ValueError) as exc:
        print(exc, file=sys.stderr)
        return 2
    print(Path(res["markdown"]).read_text())
    print(f"wrote {res['markdown']}, {res['csv']}" + "".join(f", {p}" for p in res["plots"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
