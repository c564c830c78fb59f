"""Shared fixtures: the real data folder beside the checkout, and small worlds built in code."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
sys.path.insert(0, str(Path(__file__).resolve().parent))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real-data folder; tests that need it skip when it is absent (a user's fresh clone)."""
    if not DATA.is_dir():
        pytest.skip(f"real data folder {DATA} is absent (it sits beside the checkout in CI as ../shared/data)")
    return DATA


def shared_file(*parts: str) -> Path:
    """A file of the shared real-data folder (parts joined below it); skips the calling test, with the reason,
    when the file is absent."""
    path = DATA.joinpath(*parts)
    if not path.is_file():
        pytest.skip(f"real data {path} is absent (../shared/data sits beside the checkout in CI, not in a fresh clone)")
    return path
