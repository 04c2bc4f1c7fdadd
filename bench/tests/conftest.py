"""Fixtures of the bench tools' own tests (``python -m pytest bench/tests -q``): the development data."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.lib.data import DATA_DIR


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.skip(f"development data not found at {DATA_DIR} (set POSE_DATA_DIR)")
    return DATA_DIR
