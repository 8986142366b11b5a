"""Exception types raised by morphmodes-vol.

Every error caused by user input is a subclass of :class:`ValueError`, so callers can catch
``ValueError`` without knowing this module.
"""

from __future__ import annotations

__all__ = [
    "MorphModesError",
    "MeshValidationError",
    "MeshLoadError",
    "OptionError",
    "PipelineError",
    "OpenVDBUnavailableError",
    "TargetSDFLoadError",
    "LandmarkError",
    "OutputPathError",
    "PointCloudError",
]


class MorphModesError(ValueError):
    """Base class of every input error raised by morphmodes-vol."""


class MeshValidationError(MorphModesError):
    """A mesh (vertices, faces) fails validation: wrong shape, non-finite values, bad indices."""


class MeshLoadError(MorphModesError):
    """A mesh file cannot be read: missing, empty, unsupported format or not a triangle mesh."""


class OptionError(MorphModesError):
    """An option has an invalid value (out of range, unknown literal)."""


class PipelineError(MorphModesError):
    """A pipeline definition is invalid: unreadable TOML, unknown key, missing file."""


class OpenVDBUnavailableError(MorphModesError):
    """The ``vdb`` target backend was asked for, but ``pyopenvdb`` is missing or unusable
    (for example under NumPy 2, with which Debian's OpenVDB 10 bindings crash)."""


class TargetSDFLoadError(MorphModesError):
    """A target-SDF file (``.vdb`` or ``.npz``) cannot be read or holds no usable grid."""


class LandmarkError(MorphModesError):
    """Landmarks cannot be used: unreadable or empty file, wrong column count, non-integer,
    out-of-range or duplicate source vertex index, non-finite target point."""


class OutputPathError(MorphModesError):
    """An output path cannot be used: a file where a folder is expected (or the reverse), a
    folder that cannot be created or written, or an output that would overwrite an input."""


class PointCloudError(MorphModesError):
    """A point-cloud target cannot be used: unreadable, too few or only duplicate points, NaN
    or infinite coordinates, all on a plane or a line, or normals that cannot be had."""
