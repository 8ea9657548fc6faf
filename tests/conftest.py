"""Shared pytest fixtures: the read-only shared data beside the repository (skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

#: ``<repo>/../shared/data``: teachers and other real data shared by the team (read-only).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
GUITAR_DIR = "teachers/playcanvas-guitar"


def _require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"shared data not available: {path} is absent (it lives beside the repository)")
    return path


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared data folder ``<repo>/../shared/data``; skips the test when it is absent."""
    return _require(SHARED_DATA)


@pytest.fixture(scope="session")
def guitar_ply(shared_data: Path) -> Path:
    """The PlayCanvas guitar (90,854 Gaussians, SH degree 0) in the INRIA layout, float32 little-endian."""
    return _require(shared_data / GUITAR_DIR / "point_cloud.ply")


@pytest.fixture(scope="session")
def guitar_compressed_ply(shared_data: Path) -> Path:
    """The same guitar in the PlayCanvas/SuperSplat compressed layout (the source of ``guitar_ply``)."""
    return _require(shared_data / GUITAR_DIR / "guitar.compressed.ply")
