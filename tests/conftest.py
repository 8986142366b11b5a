"""Shared fixtures: the one seeded random generator, generated meshes, the shared data dir."""

from __future__ import annotations

import os

import numpy as np
import pytest

from morphmodes_vol.datasets import shared_data_dir
from morphmodes_vol.primitives import capsule, icosphere


def _openvdb_problem() -> str | None:
    """Why the vdb backend cannot run here, or ``None`` when it can."""
    from morphmodes_vol.errors import OpenVDBUnavailableError
    from morphmodes_vol.sdf.vdb import check_openvdb

    try:
        check_openvdb()
    except OpenVDBUnavailableError as exc:
        return str(exc)
    return None


def pytest_collection_modifyitems(config, items):
    """Skip ``vdb`` tests where pyopenvdb is unusable, unless MORPHMODES_REQUIRE_VDB=1 (set by
    ``bash dev.sh test-vdb``), where they run and fail loudly instead."""
    if not any("vdb" in item.keywords for item in items):
        return
    problem = _openvdb_problem()
    if problem is None or os.environ.get("MORPHMODES_REQUIRE_VDB") == "1":
        return
    skip = pytest.mark.skip(reason=f"OpenVDB unusable here: {problem}")
    for item in items:
        if "vdb" in item.keywords:
            item.add_marker(skip)


def make_rng(seed: int = 12345) -> np.random.Generator:
    """All randomness in the tests comes from here."""
    return np.random.default_rng(seed)


@pytest.fixture
def rng() -> np.random.Generator:
    return make_rng()


@pytest.fixture
def sphere():
    return icosphere(2)


@pytest.fixture
def small_capsule():
    return capsule(height=1.0, radius=0.25, count=(12, 12))


@pytest.fixture
def lumpy_sphere():
    """An icosphere with smoothly perturbed radius: no symmetry, no medial-axis grid points."""
    V, F = icosphere(1)
    r = 1.0 + 0.15 * np.sin(3 * V[:, 0]) * np.cos(2 * V[:, 1]) + 0.1 * V[:, 2]
    return V * r[:, None], F


@pytest.fixture
def data_dir() -> Path:
    """The real meshes (``../shared/data`` or ``$MORPHMODES_DATA``). Without them a test
    skips with the reason, unless ``MORPHMODES_REQUIRE_DATA=1`` (set by ``.ci/run``, whose
    clone always has them beside it): then it fails."""
    path = shared_data_dir()
    if path is None:
        reason = "real meshes not found: ../shared/data absent and MORPHMODES_DATA unset"
        if os.environ.get("MORPHMODES_REQUIRE_DATA") == "1":
            pytest.fail(reason + " (MORPHMODES_REQUIRE_DATA=1)", pytrace=False)
        pytest.skip(reason)
    return path
