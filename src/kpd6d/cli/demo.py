"""``kpd6d-demo [overrides...]``: ``kpd6d-run experiment=demo`` (procedural objects, CPU-friendly).

Everything is made in code (objects, backgrounds, data); nothing is downloaded. The report is
written to ``outputs/demo/<date>/eval/report.md``.
"""

from __future__ import annotations

import sys


def main() -> None:
    from kpd6d.cli import run

    args = sys.argv[1:]
    if not any(a.startswith("experiment=") for a in args):
        args = ["experiment=demo", *args]
    if not any(a.startswith("hydra.run.dir=") for a in args):
        args.append("hydra.run.dir=outputs/demo/${now:%Y-%m-%d_%H-%M-%S}")
    sys.argv = [sys.argv[0], *args]
    run.main()


if __name__ == "__main__":
    main()
