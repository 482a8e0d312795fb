"""A non-editable install (the Dockerfile's) has only what the wheel holds: build the wheel
from a copy of the project, as the Docker build does, and check that every file needed at
run time is inside (the model export and its fit checkpoint, the Alembic migrations, the
web page) and the training checkpoints are not."""
from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("service", "worker", "model")
IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")


def _files(folder: str) -> set[str]:
    """Repository files under ``folder`` (posix paths relative to the root), minus caches."""
    return {p.relative_to(ROOT).as_posix() for p in (ROOT / folder).rglob("*")
            if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc"}


@pytest.fixture(scope="module")
def wheel_names(tmp_path_factory: pytest.TempPathFactory) -> set[str]:
    pytest.importorskip("setuptools", reason="the wheel is built without build isolation (no download)")
    src = tmp_path_factory.mktemp("src")
    out = tmp_path_factory.mktemp("wheel")
    for name in ("pyproject.toml", "README.md"):  # the Dockerfile's COPY lines
        shutil.copy2(ROOT / name, src / name)
    for name in PACKAGES:
        shutil.copytree(ROOT / name, src / name, ignore=IGNORE)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                           "--no-cache-dir", "-q", "-w", str(out), str(src)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (wheel,) = out.glob("texspace-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        (entry_points,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
        assert "texspace = service.cli:main" in z.read(entry_points).decode()
    return names


@pytest.mark.slow
def test_wheel_holds_the_model_export(wheel_names: set[str]) -> None:
    from service.settings import PACKAGED_MODEL_DIR

    # the settings default points into the package, so it is in site-packages after install
    assert PACKAGED_MODEL_DIR.relative_to(ROOT).as_posix() == "model/weights"
    for name in ("encoder.onnx", "sampler.onnx", "manifest.json", "MODEL_CARD.md", "space.pt"):
        assert f"model/weights/{name}" in wheel_names
    assert _files("model/weights") <= wheel_names


@pytest.mark.slow
def test_wheel_holds_migrations_and_web_page(wheel_names: set[str]) -> None:
    for name in ("service/alembic/env.py", "service/alembic/script.py.mako",
                 "service/static/index.html"):
        assert name in wheel_names
    assert any(n.startswith("service/alembic/versions/0001_") for n in wheel_names)
    missing = (_files("service/alembic") | _files("service/static")) - wheel_names
    assert not missing, sorted(missing)


@pytest.mark.slow
def test_wheel_holds_all_code(wheel_names: set[str]) -> None:
    code = {n for p in PACKAGES for n in _files(p) if n.endswith(".py")}
    missing = {n for n in code if not n.startswith("model/checkpoints/")} - wheel_names
    assert not missing, sorted(missing)
    assert not [n for n in wheel_names if n.startswith("model/checkpoints/")]  # training only
