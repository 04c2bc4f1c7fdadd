"""Shared fixtures: the development data in ../shared/data and the project's meshes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("POSE_DATA_DIR", ROOT.parent / "shared" / "data"))
MODELS_DIR = DATA_DIR / "models"
# In-process apps (TestClient) skip the start-up warm-up: dozens of them would each run the pipeline
# once; the served processes (tests/test_serve.py builds their environment itself) keep it on.
os.environ.setdefault("POSE_WARM_UP", "false")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.skip(f"development data not found at {DATA_DIR} (set POSE_DATA_DIR)")
    return DATA_DIR


@pytest.fixture(scope="session")
def sprayer_mesh(data_dir):
    import trimesh

    return trimesh.load(data_dir / "models" / "sprayer.stl", force="mesh")


@pytest.fixture(scope="session")
def tless06_mesh(data_dir):
    import trimesh

    return trimesh.load(data_dir / "models" / "tless_06.ply", force="mesh")


@pytest.fixture(scope="session")
def sprayer_bytes(data_dir) -> bytes:
    return (data_dir / "models" / "sprayer.stl").read_bytes()
