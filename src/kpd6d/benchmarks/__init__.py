"""Benchmarks printed by ``kpd6d-benchmark <name>``; each module here has ``main(argv) -> int``."""
