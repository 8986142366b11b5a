"""Fixed subspace: the SDF energy of Eq. (3) in a fixed subspace of ``k`` skinning
eigenmodes, all active from the first iteration (one stage; the paper's "fixed, small
subspace" and "fixed, large subspace, for instance 70 modes")."""

from __future__ import annotations

from ..mesh import MeshLike
from ..options import RegistrationOptions
from ..register import RegistrationResult, register

__all__ = ["fixed_subspace"]


def fixed_subspace(
    source: MeshLike,
    target: MeshLike,
    modes: int,
    *,
    options: RegistrationOptions | None = None,
    ground_truth=None,
    progress=None,
) -> RegistrationResult:
    """Register in a fixed subspace of ``modes`` skinning eigenmodes.

    Runs :func:`~morphmodes_vol.register` with ``modes=initial_modes=modes`` and a stage
    cap equal to ``options.max_iterations`` (for either optimizer), so the single stage ends
    only by the stall tests, a step without decrease or the iteration cap.

    Returns
    -------
    RegistrationResult
        Same conventions as :func:`~morphmodes_vol.register`.

    Examples
    --------
    >>> from morphmodes_vol.primitives import capsule
    >>> V, F = capsule(count=(8, 8))
    >>> r = fixed_subspace((V, F), (V * 1.05, F), 3, options=RegistrationOptions(grid=12, max_iterations=4))
    >>> r.modes, len(r.history.stage_ends)
    (3, 1)
    """
    options = options if options is not None else RegistrationOptions()
    options = options.replace(modes=modes, initial_modes=modes,
                              max_iterations_per_stage=options.max_iterations,
                              lm_iterations_per_stage=options.max_iterations,
                              lm_final_iterations=options.max_iterations)
    return register(source, target, options, ground_truth=ground_truth, progress=progress)
