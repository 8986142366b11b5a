"""Shared fixtures: the one seeded random generator, generated meshes, the shared data dir."""

from __future__ import annotations

import numpy as np
import pytest

from morphmodes_vol.datasets import shared_data_dir
from morphmodes_vol.primitives import capsule, icosphere


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
    path = shared_data_dir()
    if path is None:
        pytest.skip("real meshes not found: ../shared/data absent and MORPHMODES_DATA unset")
    return path
