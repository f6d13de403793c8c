"""`pip install .` (not only editable) ships the Hydra configs and every CLI finds them."""

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_ships_configs_and_cli_finds_them(tmp_path):
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w",
                    str(tmp_path / "whl"), str(ROOT)], check=True, capture_output=True, timeout=300)
    (wheel,) = (tmp_path / "whl").glob("kpd6d-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    conf_files = sorted(p.relative_to(ROOT / "conf").as_posix() for p in (ROOT / "conf").rglob("*.yaml"))
    assert conf_files and all(f"kpd6d/conf/{c}" in names for c in conf_files)
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(tmp_path / "site"),
                    str(wheel)], check=True, capture_output=True, timeout=300)
    code = ("import sys; sys.argv = ['kpd6d-train', '--cfg', 'job', 'stage=detector', 'detector=oracle']\n"
            "import kpd6d.config; print(kpd6d.config.config_dir())\n"
            "from kpd6d.cli.train import main; main()")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300,
                         env={"PYTHONPATH": str(tmp_path / "site"), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.splitlines()[0] == str(tmp_path / "site" / "kpd6d" / "conf")
    assert "name: oracle" in out.stdout
