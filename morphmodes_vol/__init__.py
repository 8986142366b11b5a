"""morphmodes-vol: non-rigid registration of triangle meshes by SDF matching in an adaptive
skinning-eigenmode subspace (MorphModes, Eurographics 2026).

Quick use::

    import morphmodes_vol as mm
    result = mm.register("source.obj", "target.obj", grid=64, modes=20)
    result.vertices          # (n, 3) registered source vertices, original frame and order
"""

from .export import write_outputs
from .errors import MeshLoadError, MeshValidationError, MorphModesError, OptionError
from .mesh import as_mesh, load_mesh, validate_mesh
from .options import RegistrationOptions
from .register import Registration, RegistrationResult, ground_truth_error, register
from .landmarks import LandmarkError, Landmarks, load_landmarks

__version__ = "0.1.0"

__all__ = [
    "register",
    "Registration",
    "RegistrationResult",
    "RegistrationOptions",
    "ground_truth_error",
    "write_outputs",
    "load_mesh",
    "validate_mesh",
    "as_mesh",
    "MorphModesError",
    "MeshValidationError",
    "MeshLoadError",
    "OptionError",
    "Landmarks",
    "load_landmarks",
    "LandmarkError",
    "__version__",
]
