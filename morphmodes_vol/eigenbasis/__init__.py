"""Stage 2, the eigenbasis: cotangent Laplacian, lumped mass, skinning eigenmodes (Eq. 4)
and the implicit LBS basis (Eq. 5-6)."""

from .component_coupling import component_coupling
from .cotangent_laplacian import cotangent_laplacian
from .lbs import LBSBasis, from_paper_z, to_paper_z
from .lumped_mass import lumped_mass
from .mesh_weights import mesh_skinning_weights
from .skinning_eigenmodes import skinning_eigenmodes

__all__ = [
    "cotangent_laplacian",
    "lumped_mass",
    "component_coupling",
    "skinning_eigenmodes",
    "mesh_skinning_weights",
    "LBSBasis",
    "to_paper_z",
    "from_paper_z",
]
