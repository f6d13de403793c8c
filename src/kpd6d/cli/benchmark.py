"""``kpd6d-benchmark NAME [options]``: run a benchmark of :mod:`kpd6d.benchmarks` and print its figures.

Each benchmark is a module ``kpd6d.benchmarks.NAME`` with ``main(argv: list[str]) -> int``;
``kpd6d-benchmark NAME --help`` shows its options.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys

import kpd6d.benchmarks as _pkg


def available() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(_pkg.__path__) if not m.name.startswith("_"))


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    names = available()
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        print("\navailable benchmarks: " + ", ".join(names))
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in names:
        print(f"kpd6d-benchmark: unknown benchmark {name!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    return int(importlib.import_module(f"kpd6d.benchmarks.{name}").main(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
