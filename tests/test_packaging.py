"""What an installed (not editable) posegrid needs besides its Python files ships with it.

A probe installed posegrid with `pip install .` (as the Dockerfile does): the wheel held no services/api/static (no
package-data), so `posegrid api`, and `posegrid run` with its API, could not start. Building a wheel needs the build
backend from the network, so this reads pyproject.toml's package-data instead and checks it names every file of
the packages that is not Python."""

from __future__ import annotations

import fnmatch
import os
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # (Python 3.10)
    tomllib = pytest.importorskip("tomli", reason="reading pyproject.toml needs tomllib (3.11) or tomli")

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("mapping", "slam", "schemas", "services")


def _data_files() -> list[Path]:
    """Every file under the packages that Python does not import (numba's and Python's caches left out)."""
    found = []
    for package in PACKAGES:
        for folder, folders, files in os.walk(ROOT / package):
            folders[:] = [name for name in folders if name != "__pycache__"]
            found += [Path(folder, name) for name in files if not name.endswith((".py", ".pyc"))]
    return found


def _shipped(path: Path, package_data: dict[str, list[str]]) -> bool:
    """Whether a package-data pattern of a package above ``path`` takes it in (setuptools' globs, relative to the
    package's folder)."""
    relative = path.relative_to(ROOT)
    for depth in range(1, len(relative.parts)):
        package, inside = ".".join(relative.parts[:depth]), "/".join(relative.parts[depth:])
        if any(fnmatch.fnmatchcase(inside, pattern) for pattern in package_data.get(package, [])):
            return True
    return False


def test_every_data_file_of_the_packages_is_package_data():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    package_data = config.get("package-data", {})
    files = _data_files()
    assert any(path.name == "index.html" for path in files)  # (the viewer's page: the walk finds the files)
    missing = [str(path.relative_to(ROOT)) for path in files if not _shipped(path, package_data)]
    assert not missing, f"not in [tool.setuptools.package-data], so not in a wheel: {missing}"
