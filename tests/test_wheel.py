"""A plain `pip install` of the wheel works anywhere: it carries the presets, and `splatk demo`
(the README's first command) runs from a folder outside the repository.

Builds the wheel without build isolation and installs it with ``--no-deps`` into a fresh
virtual environment that sees this interpreter's packages (torch and the rest need no
download), then runs the installed ``splatk`` from a temporary folder.
"""
from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: what the wheel is built from (pyproject.toml names each); nothing else of the tree is copied
SOURCES = ("pyproject.toml", "README.md", "src", "cli", "presets")

pytestmark = pytest.mark.wheel


def _can_build_wheels() -> bool:
    """setuptools >= 70.1 builds wheels itself; older ones need the `wheel` package."""
    try:
        import setuptools
    except ImportError:
        return False
    major, minor = (int(x) for x in setuptools.__version__.split(".")[:2])
    if (major, minor) >= (70, 1):
        return True
    try:
        import wheel  # noqa: F401
    except ImportError:
        return False
    return True


def _run(cmd: list, cwd: Path, env: dict | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    res = subprocess.run([str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"{' '.join(map(str, cmd))} exited {res.returncode}:\n{res.stdout}\n{res.stderr}"
    return res


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """The bin/ folder of a fresh virtual environment holding only the splatk wheel."""
    if not _can_build_wheels():
        pytest.skip("building a wheel without build isolation needs setuptools>=70.1 (pip install -U setuptools)")
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.so", "build")
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=ignore)
        else:
            shutil.copy2(path, src / name)
    dist = tmp / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
          ".", "-w", dist], cwd=src)
    (wheel,) = dist.glob("splatk-*.whl")

    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", venv], cwd=tmp)
    py = venv / "bin" / "python"
    purelib = _run([py, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=tmp).stdout.strip()
    # when this interpreter is itself a virtual environment, its packages (torch, click, pip, ...)
    # live beside it rather than in the base installation the new one sees
    (Path(purelib) / "_parent_site.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    _run([py, "-m", "pip", "install", "--no-deps", "--no-index", "-q", wheel], cwd=tmp)
    return venv / "bin"


def _env(bin_dir: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env.update(PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}", OMP_NUM_THREADS="1")
    return env


def test_wheel_runs_its_own_code(installed, tmp_path):
    res = _run([installed / "python", "-c", "import splatk, splatk_cli; print(splatk.__file__); print(splatk_cli.__file__)"],
               cwd=tmp_path, env=_env(installed))
    venv = installed.parent.resolve()
    for line in res.stdout.split():
        assert venv in Path(line).resolve().parents, f"{line} is not the installed wheel's copy"


def test_wheel_carries_the_presets(installed, tmp_path):
    res = _run([installed / "python", "-c", "from splatk_cli.common import PRESET_DIRS, find_preset; "
                "print(find_preset('demo')); print(find_preset('bench_quick'))"], cwd=tmp_path, env=_env(installed))
    venv = installed.parent.resolve()
    for line in res.stdout.split():
        assert venv in Path(line).resolve().parents and Path(line).is_file(), line


def test_demo_runs_outside_the_repository(installed, tmp_path):
    env = _env(installed)
    res = _run([installed / "splatk", "--help"], cwd=tmp_path, env=env)
    assert "demo" in res.stdout and "fit" in res.stdout
    out = tmp_path / "demo"
    res = _run([installed / "splatk", "demo", "--out", out, "--iters", "30"], cwd=tmp_path, env=env, timeout=420)
    assert (out / "run" / "model.pt").is_file(), res.stdout + res.stderr
    assert (out / "run" / "metrics.json").is_file()
    assert (out / "model.ply").stat().st_size > 0
