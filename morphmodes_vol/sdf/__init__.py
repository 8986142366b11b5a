"""Signed distance fields: regular grids and trilinear sampling, the target SDF (built once;
dense or OpenVDB backend, see :mod:`.target`), and the source SDF (Open3D queries on the
deformed source at every evaluation)."""

from .closest_point import closest_point_barycentrics
from .grid import Grid, trilinear_sample
from .source import ClosestPoints, SignedDistanceQuery, closest_points, inside, signed_distance, signed_volume
from .target import (
    TARGET_BACKENDS,
    DenseTargetSDF,
    TargetBackend,
    TargetSDF,
    build_target_sdf,
    is_target_sdf_path,
    load_target_sdf,
)

__all__ = [
    "Grid",
    "trilinear_sample",
    "closest_point_barycentrics",
    "ClosestPoints",
    "SignedDistanceQuery",
    "closest_points",
    "signed_volume",
    "inside",
    "signed_distance",
    "DenseTargetSDF",
    "TargetSDF",
    "TargetBackend",
    "TARGET_BACKENDS",
    "build_target_sdf",
    "is_target_sdf_path",
    "load_target_sdf",
]
