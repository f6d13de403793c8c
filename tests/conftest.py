"""Shared fixtures. Real data lives in ../shared/data (or $KPD6D_SHARED_DATA); it is never needed by
the library itself. In CI (CI=true) a missing shared folder is an error, never a silent skip."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _absl_logs_to_the_real_stderr() -> None:
    """absl (pulled in by the ONNX / OpenVINO stack) gives its log handler the sys.stderr of the moment
    it is imported: inside a test, pytest's capture stream. Its ``close()`` closes any stream that is not
    the *current* sys.stderr, and a later Hydra CLI test reconfigures logging, which closes every handler:
    pytest's capture stream then dies ("lost sys.stderr", depending on how xdist orders the tests).
    Importing it here and pointing it at the real stderr (never closed) removes the order dependence."""
    import sys

    try:
        from absl import logging as absl_logging
    except ImportError:
        return
    absl_logging.get_absl_handler().python_handler.stream = sys.__stderr__


_absl_logs_to_the_real_stderr()


def shared_data_dir() -> Path:
    env = os.environ.get("KPD6D_SHARED_DATA")
    return Path(env) if env else ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    d = shared_data_dir()
    if not (d / "lmo" / "models" / "models_info.json").is_file():
        msg = f"shared LM-O data not found at {d} (set KPD6D_SHARED_DATA)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return d


@pytest.fixture(scope="session")
def lmo_dir(shared_data: Path) -> Path:
    return shared_data / "lmo"


@pytest.fixture(scope="session")
def lmo_models(lmo_dir: Path):
    from kpd6d.objects import load_bop_models

    return load_bop_models(lmo_dir / "models")


@pytest.fixture(scope="session")
def lmo_model_by_id(lmo_models):
    return {m.obj_id: m for m in lmo_models}


@pytest.fixture
def one_torch_thread():
    """One torch thread for the test: ``pytest -n 2`` already fills both cores, so more threads per
    worker only contend. Use with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
