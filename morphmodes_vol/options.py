"""Every tunable of a registration, as frozen dataclasses with named fields.

Units: all lengths are in the *normalized* frame, in which the union bounding box of source
and target has a diagonal of 1 (see :mod:`morphmodes_vol.mesh`). A length of ``0.01`` is
therefore 1% of the size of the scene, whatever the units of the input files.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from importlib import resources
from dataclasses import dataclass
from typing import Literal

from .errors import OptionError
from .sdf.points import POINT_SDF_METHODS, PointSDFMethod
from .sdf.source import SignMethod
from .sdf.target import TARGET_BACKENDS, TargetBackend

__all__ = ["RegistrationOptions", "parse_setting", "preset_table", "preset_description", "Preconditioner", "PRECONDITIONERS", "SIGN_METHODS", "Optimizer",
           "OPTIMIZERS", "Quadrature", "QUADRATURES", "Initialization", "INITIALIZATIONS", "WarpedChoice",
           "WARPED_CHOICES"]

Preconditioner = Literal["block", "none"]
PRECONDITIONERS = typing.get_args(Preconditioner)
SIGN_METHODS = typing.get_args(SignMethod)
SourceSign = Literal["auto", "raycast", "winding"]
SOURCE_SIGNS = typing.get_args(SourceSign)
Optimizer = Literal["lm", "paper"]
OPTIMIZERS = typing.get_args(Optimizer)
Quadrature = Literal["full", "band"]
QUADRATURES = typing.get_args(Quadrature)
Initialization = Literal["none", "rigid", "similarity"]
INITIALIZATIONS = typing.get_args(Initialization)
WarpedChoice = Literal["objective", "field", "both"]
WARPED_CHOICES = typing.get_args(WarpedChoice)
Preset = Literal["default", "fast", "fastest", "paper"]
PRESETS = typing.get_args(Preset)


@dataclass(frozen=True)
class RegistrationOptions:
    """Options of :func:`morphmodes_vol.register`.

    Attributes
    ----------
    grid : int
        Number of quadrature points along the longest side of the padded box (Eq. 3); the
        other sides get the same spacing. ``64`` gives about 67k points on the lion.
    target_grid : int or None
        Nodes of the dense target-SDF grid along the longest side; ``None`` uses ``grid``.
    quadrature : {"full", "band"}
        ``"full"`` (default): every grid node, Eq. (3) as in the paper. ``"band"`` (the fast
        settings): every node within ``band_cells`` grid spacings of either surface and one
        node per block of ``block_factor^3`` nodes elsewhere, weighted by the block's volume
        (:mod:`morphmodes_vol.quadrature`): fewer closest-point queries, but the far blocks'
        gradient is a coarse sample of the nodes', which moves the optimum where the residual
        is small and makes the runs follow the band's refreshes (docs/decisions/0004).
    band_cells : float
        Half width of the fine band, in grid spacings; also the band around an open target
        within which its field is trusted on both sides (:mod:`morphmodes_vol.sdf.confidence`).
    block_factor : int
        Nodes per block side away from the surfaces (``"band"`` quadrature). ``2`` (default):
        with ``4`` (the default until 2026-11-30) the demo pair ended 7-20x farther from its
        known answer (docs/method.md, "Band quadrature").
    band_margin_cells : float
        Vertex motion, in grid spacings, after which the band is recomputed.
    padding : float
        Margin added on every side of the union bounding box, as a fraction of its diagonal.
    coarse_modes : int
        A grid that refines across stages: the first ``coarse_modes`` stages of Algorithm 1
        evaluate Eq. (3) on every other node of the quadrature grid (spacing ``2h``, the same
        ``quadrature`` kind), the later ones on the full resolution. ``0`` (default): one grid
        throughout.
    modes : int
        ``m_max``, the largest number of skinning eigenmodes (12 degrees of freedom each).
    initial_modes : int
        Modes active from the start. Algorithm 1 starts with ``1`` (a global affine map,
        the default); ``initial_modes == modes`` optimizes in a *fixed* subspace of
        ``modes`` modes in one stage (the fixed-subspace baseline of the paper's
        "Necessity of adaptive scheme"; ``morphmodes_vol.baselines.fixed_subspace``).
    stall_start, stall_end : float
        Stall threshold ``eps_stall`` of Algorithm 1 for the first and the last stage; stages
        in between decay geometrically. Measured as the root-mean-square vertex motion of
        one iteration in normalized units, so the schedule does not depend on the vertex
        count (the paper's 1e-1 to 1e-3 on the 2-norm of all 3n coordinates correspond to
        about 1.4e-3 to 1.4e-5 RMS on its 5000-vertex lion).
    max_iterations_per_stage : int
        Cap on the gradient steps of one stage before the next mode is added anyway
        (``optimizer="paper"``).
    max_iterations : int
        Cap on the gradient steps of the whole run.
    max_step : float
        RMS vertex motion (normalized units) of the first trial step of each stage, and the
        most any trial step may move the vertices. Later iterations start their line search
        from the previous accepted step (doubled when it needed no backtracking).
    armijo : float
        Sufficient-decrease constant ``c`` of the backtracking line search.
    backtrack : float
        Step shrink factor of the backtracking line search, in (0, 1).
    max_backtracks : int
        Trial steps of one line search before the stage is declared stalled.
    optimizer : {"lm", "paper"}
        Step taken in the active subspace. ``"lm"`` (default): Levenberg-Marquardt on the
        Gauss-Newton model with frozen closest-point correspondences, accepted on the true
        energy (docs/method.md), 10-16x fewer SDF evaluations than ``"paper"``:
        Algorithm 1's gradient step with a backtracking line search (see
        ``preconditioner``). Both use the same modes and stall schedule.
    lm_damping : float
        Initial Levenberg-Marquardt damping, relative to the scale of the normal equations
        (dimensionless); adapted by Nielsen's rule during the run.
    lm_max_step : float
        Largest RMS vertex motion (normalized units) of one Levenberg-Marquardt step.
    lm_iterations_per_stage : int
        Cap on the Levenberg-Marquardt steps of one stage (``max_iterations_per_stage`` is
        the gradient optimizer's). Few on purpose: converging early stages fully raised the
        ground-truth error on the lion (docs/method.md).
    lm_final_iterations : int or None
        Cap on the Levenberg-Marquardt steps of the last stage (``modes`` modes); ``None``
        (default): ``lm_iterations_per_stage``, as every stage. With one step per stage
        (``lm_iterations_per_stage=1``, the schedule measured in docs/method.md, "Steps per
        stage and modes") a cap of 5 lets the last stage run until the stall tests end it,
        so the result is the full subspace's optimum rather than one step towards it.
    lm_stall_decrease : float
        A Levenberg-Marquardt stage also ends when one step lowers the energy by less than
        this fraction of it (``0`` turns the test off).
    preconditioner : {"block", "none"}
        ``"block"`` (default) scales each mode's 3x4 block of the gradient by the inverse of
        its 4x4 Gram matrix ``[X0 1]^T diag(w_j)^2 [X0 1]`` (our one deviation from the
        paper's plain gradient step, see docs/method.md); ``"none"`` is the paper's step.
    source_sign : {"auto", "raycast", "winding"}
        Inside test of the deformed source at every evaluation. ``"raycast"``: Open3D ray
        parity, exact for closed sources; ``"winding"``: generalized winding number (libigl),
        robust for open sources (holes, a mask, parts); ``"auto"`` (default): ray parity for a
        closed source (every edge shared by two triangles), the winding number otherwise, so
        the choice follows the topology, which a rounding error or another triangulation of
        the same closed surface does not change.
    occupancy_samples : int
        Rays cast (odd; majority vote) by the ``"raycast"`` inside test.
    seed : int
        Seed of the only random choice (the start vector of the sparse eigensolver).
    memory_limit_gb : float or None
        Refuse, before any heavy work, a registration whose estimated peak memory
        (:mod:`morphmodes_vol.limits`: vertices, modes, grid sizes) exceeds this many GB;
        ``None`` disables the check. A lion pair at ``grid=64`` is estimated at 0.3 GB.
    target_backend : {"dense", "vdb"}
        Storage of the target SDF (docs/target_sdf.md): ``"dense"`` (default) a regular grid;
        ``"vdb"`` a narrow-band OpenVDB level set with voxel size equal to the dense grid's
        spacing and the exact distance outside the band (needs ``bash dev.sh vdb-env``).
        Ignored when the target is given as an SDF file (its type decides).
    target_sign : {"winding", "raycast"}
        Inside test of the target, negative inside. ``"winding"`` (default, chosen by the
        holed-sphere measurement of docs/target_sdf.md): generalized winding number, right
        behind holes; ``"raycast"``: Open3D ray parity, wrong in a shadow behind each hole.
    point_sdf : {"winding", "poisson"}
        How a point-cloud target is made a field (:mod:`morphmodes_vol.sdf.points`):
        ``"poisson"`` (default), its screened Poisson surface, trimmed where no point is near,
        registered onto as a mesh (with the descriptors a mesh target has); ``"winding"``, directly, the distance to the nearest point's tangent
        disc signed by the fast winding number of the oriented points, registered onto as an
        SDF target.
    vdb_half_width : float
        Half width of the ``"vdb"`` band in voxels (OpenVDB's default, 3).
    landmark_weight : float
        Weight of the landmark term, when landmarks are given (:mod:`morphmodes_vol.landmarks`):
        dimensionless, ``1`` makes the mean squared landmark distance count as much as the
        mean squared SDF residual over the quadrature box; ``0`` ignores the landmarks.
    initialization : {"none", "rigid", "similarity"}
        Global alignment before Algorithm 1 (:mod:`morphmodes_vol.initialize`): a rigid
        motion or similarity minimizing Eq. (3) on a coarse grid, refined from the source's
        own orientation (centroids matched) and from the best of 28 candidate orientations.
        ``"none"``: start at the rest pose, as the paper does.
    init_grid : int
        Nodes along the longest side of the coarse grid of the initialization.
    init_candidates : int
        Starts refined: the unrotated one and the ``init_candidates - 1`` best screened
        rotations (``1``: no multi-start, a local alignment only).
    init_switch : float
        A rotated start wins only when its energy is below ``init_switch`` times the
        unrotated start's (an orientation prior; docs/method.md has the measurements).
    init_keep_rest : bool
        With an initialization, run Algorithm 1 from the rest pose (the paper's start) as
        well as from the aligned start, and keep the
        result that stretches the source's edges least
        (:func:`morphmodes_vol.metrics.edge_strain`) among those whose objective (Eq. 3 on
        the full grid plus the isometry prior and landmarks when on) is within
        ``select_energy_factor`` of the lowest; ``False`` runs from the aligned start only.
    coarse_starts : bool
        Run the starts on every other node of the quadrature grid (spacing ``2h``, an eighth
        of the points), and keep the run that the rule among starts chooses there; the grid
        itself is the warped pass's, whose refinements run on it. ``True`` (default);
        ``False``: the starts on the grid itself, as grids under 48 nodes always run.
    overlap_field : bool
        With ``warped_pass``: make the descriptor channels (beside the initialization), then
        minimize the warped rest field from the starts (numpy, no source query), on a second
        thread while Algorithm 1 runs from them, instead of after it. The same results but
        for the last bits of some BLAS products (usually bit for bit on the test pair; on the
        accuracy study one error of 30 moved, by 0.3%); ``True`` (default) is faster with two
        cores or more: lion-05 26.6 s against 30.6 (docs/method.md, "The warped rest field
        beside the runs").
    select_energy_factor : float
        See ``init_keep_rest``; at least 1 (``1``: the lowest objective). With the isometry
        prior, every factor from 1.25 to 10 kept the same start on the 18 poses
        (docs/method.md).
    start_check_modes : int
        With several starts, the runs advance in lockstep, one mode at a time, and from this
        many modes on a run stops early when another makes it redundant (the two tests
        below, pair by pair). Above ``modes``: never. The defaults were read off the 30 pairs
        of the accuracy study (docs/method.md, "Initialization and two starts", items 6 and
        9).
    start_merge_distance : float
        Two runs' vertices are closer than this RMS distance to each other (normalized
        units): the one that stretches the edges more stops. ``0``: never merged.
    start_strain_ratio : float
        A run's edge strain is more than this times another's, and the other's objective
        is within ``select_energy_factor`` of its own: it stops (the final selection would
        not keep it). ``inf``: never.
    start_choice_modes : int or None
        With several starts still running after this many modes, the final choice
        (``init_keep_rest``) is made there and only the chosen run goes on to ``modes``: the
        deep modes refine one run, not several (with ``modes=30``, the accuracy study's mean
        fell by 5% at 22% more evaluations; docs/method.md, "More modes"). At or above
        ``modes`` (as with the default 20 modes), or ``None``: the choice is made at the end.
    isometry_weight : float
        Weight of the isometry prior (:mod:`morphmodes_vol.isometry`), added to Eq. (3): a
        penalty on the edges whose log stretch differs from the surface's mean by more than
        ``isometry_tolerance``, zero for rigid motions and uniform scaling. Unit: squared
        normalized length (``E_iso / V`` against ``E_sdf / V``, the mean squared SDF residual):
        with ``3e-4`` (default, set by the 18-pose study of docs/method.md) an excess log
        stretch ``s`` everywhere costs as much as an SDF residual of ``0.017 s`` of the
        diagonal everywhere. ``0``: Eq. (3) alone, as in the paper.
    isometry_tolerance : float
        Deviation of an edge's log stretch from the mean that costs nothing (``0.2``: about
        +-20%), so shapes that differ by moderate stretch (a capsule stretched by 1.2 and
        bent) register as well as without the prior (docs/method.md).
    init_lm_iterations_per_stage : int
        ``lm_iterations_per_stage`` of the run from the aligned start (the rest start keeps
        ``lm_iterations_per_stage``). 3, as for the rest start: on the 18 lion and cat poses
        the kept result's mean ground-truth error was 0.100 with 3, 0.103 with 5 and 0.109
        with 10, and from starts turned by 2 degrees about random axes lion-05 ended at
        0.08-0.13 with 3 but at 0.09-0.53 with 10 (docs/method.md).
    warped_pass : bool
        After the runs, minimize the warped rest field from every start (and from the
        initialization's other orientations, ``warped_candidates``)
        (:mod:`morphmodes_vol.warped_field`: Eq. 2 pulled back to the rest pose, the rest
        source's signed distance carried by the subspace, with no source query after one at
        the start), refine the result picked by ``warped_choice`` by Levenberg-Marquardt on
        Eq. (3) with all modes (at most ``warped_polish_iterations`` steps), and keep it when its
        objective is lower than the runs' result (for a candidate's, by the factor
        ``warped_candidate_ratio``; docs/method.md, "The warped rest field"). On (default):
        on the accuracy study's 30 pairs the mean ground-truth error fell from 0.0490 to
        0.0329 (three starts), at 19.9 s per pair against 12.8, and to 0.0279 with the
        defaults of ``warped_candidates`` and ``warped_choice`` (24.3 s). ``False``: the
        runs only (off in :meth:`paper_faithful`).
    field_only : bool
        With ``warped_pass``: no run of Algorithm 1 on Eq. (3) from the starts; the warped
        rest field alone is minimized from them, and the result of lowest field energy is
        refined on Eq. (3) (``warped_polish_iterations`` steps) and kept, then hopped from
        as ``warped_hops`` and ``warped_descriptors`` ask. The fastest setting
        (:meth:`fastest`) turns it on: the runs are most of the defaults' time (docs/method.md,
        "The fastest setting"). ``False`` (default).
    warped_band_cells : float
        The warped rest field's band: grid nodes (the quadrature's spacing) within this many
        spacings of the rest surface.
    warped_iterations_per_stage : int
        Levenberg-Marquardt steps per mode on the warped rest field (3: mean 0.0329 on the
        accuracy study at 19.9 s per pair; 5: 0.0346 at 21.4 s).
    warped_polish_iterations : int
        Levenberg-Marquardt steps on Eq. (3) from the warped rest field's result (one stage
        with all modes; it stops earlier when a step no longer decreases the objective).
    warped_candidates : bool
        Also minimize the warped rest field from the initialization stage's other refined
        candidates (other orientations; those that map the source within
        ``start_merge_distance`` of a start already taken are skipped). No source query:
        about 1.5 s per candidate on the lion. On (default): with ``warped_choice="field"``
        the accuracy study's mean fell from 0.0329 to 0.0279 (cat-04 0.223 -> 0.073, from
        a candidate turned by about 11 degrees from the truth's orientation where the
        chosen alignment was 163 degrees off; docs/method.md, "The warped rest field").
    warped_candidate_ratio : float
        The orientation prior of the warped pass (as ``init_switch`` is the
        initialization's): a refined result that came from a candidate (another
        orientation) is kept only when its objective is below this times that of every
        result from the starts (the runs' result and, refined too whenever a candidate
        ranks first, the best start's field result). Shapes with a symmetry tie across
        orientations: on a capsule turned end over end the candidate's objective was 0.05%
        lower and its ground-truth error 0.77 against 0.024; on cat-04 the kept candidate's
        objective is 0.68 times the runs'. 0.95; not tuned further.
    warped_choice : {"objective", "field", "both"}
        Which field results are refined on Eq. (3): the one of lowest objective (Eq. 3 on
        the full grid, one evaluation per field result), the one of lowest field energy
        ``E_w`` (no evaluation), or both (one refinement when they are the same).
        ``"field"`` (default): with the candidates, the same mean as ``"both"`` on the
        accuracy study (0.0279 against 0.0278) without an evaluation per field result.
    warped_refine : int
        How many field results ``warped_choice`` picks by each of its rankings (the lowest
        ``warped_refine``): each is refined, and the refined results compete with the runs'
        result as ``warped_candidate_ratio`` says (2: the same study mean, 0.0278, at 26 s
        per pair against 24).
    warped_prune_modes : int
        The warped pass minimizes the field from every start to this many modes first; only
        the results whose field energy ``E_w`` is at most ``warped_prune_ratio`` times the
        lowest go on to ``modes`` (0, or at least ``modes``: every start to the end). A
        stage's matrices grow with the square of the active modes, so a start stopped at 8
        of 20 modes has cost a small part of a whole run. 8 (default): measured on the
        accuracy study's 30 pairs (187 field starts), the start of lowest ``E_w`` at 20
        modes had at 8 modes at most 1.24 times the lowest ``E_w``, and a ratio of 2 stops
        74 starts there; the same 30 errors at 17.7 s per pair against 24.3 (docs/method.md,
        "Stopping field starts early").
    warped_prune_ratio : float
        See ``warped_prune_modes`` (at least 1).
    warped_hops : int
        After the warped pass has chosen its result (the runs' or a refined field result),
        at most this many *hops* through the field's landscape: the field ``E_w`` minimized
        from the kept result with all modes at once (at most ``warped_hop_iterations``
        Levenberg-Marquardt steps), then refined on Eq. (3) as a field result is
        (``warped_polish_iterations``), kept when its objective is below
        ``warped_hop_ratio`` times the kept result's, the next hop from there; the hops end
        at the first not kept. The two energies have different local minima, so a result
        stuck in one's can leave it through the other's: 0.0279 -> 0.0256 on the accuracy
        study, 2 or 3 hops the same (docs/method.md, "Hops through the field"). 0: none.
    warped_hop_iterations : int
        The field's Levenberg-Marquardt steps of a hop (at least 1).
    warped_hop_ratio : float
        A hop is kept only when its objective is below this times the result it left (in
        (0, 1]). Where the objective is flat (a capsule turns freely about its axis) a hop
        can drift along the valley: onto an OpenVDB target a hop at 0.9996 times the
        objective doubled the ground-truth error. 0.99: on the accuracy study the hops kept
        above 0.99 moved no error by more than 0.0008 (docs/method.md, "Hops through the
        field").
    warped_descriptors : bool
        After the hops, one *descriptor hop*: the field with descriptor channels (the heat
        kernel signatures of both meshes, :mod:`morphmodes_vol.descriptors`: a part must land
        on the part of the target of its own shape) minimized from the kept result with all
        modes (``warped_hop_iterations`` steps), refined on Eq. (3) and kept below
        ``warped_hop_ratio`` times the objective, as a hop: 0.0256 -> 0.0204 on the accuracy
        study (docs/method.md, "Descriptors in the warped field"). Needs a target mesh
        (skipped for an SDF target).
    warped_descriptor_weight : float
        ``mu``: the weight of the descriptors' mean squared residual (log heat kernel
        signature, unitless) against the SDF's squared residual (non-negative).
    two_way : bool
        Also register the target onto the source (these options, one way), read the
        correspondences off that reverse registration (:mod:`morphmodes_vol.two_way`), fit the
        ``modes`` modes to them in two ways and minimize the objective from each fit by
        Levenberg-Marquardt on all modes; keep the lowest objective among these two results
        and the forward one (docs/method.md, "Two-way registration"). About twice the time;
        on the accuracy study's 30 pairs the mean ground-truth error fell from 0.0490 to
        0.0344 (28 s per pair against 13). Needs the target as a mesh. ``False`` (default):
        the forward registration only.
    two_way_iterations : int
        The Levenberg-Marquardt steps of each run from the reverse correspondences (one stage
        with all modes; it stops earlier when a step no longer decreases the objective).
    two_way_grid : int or None
        ``grid`` of the reverse registration (its result only places the correspondences;
        the runs from them use ``grid``). ``None`` (default): ``grid``. ``32`` with the
        default grid 64: 23 s per pair of the accuracy study against 28, mean error 0.0375
        against 0.0344 (docs/method.md, "Two-way registration").
    """

    grid: int = 64
    target_grid: int | None = None
    quadrature: Quadrature = "full"
    band_cells: float = 2.0
    block_factor: int = 2
    band_margin_cells: float = 4.0
    padding: float = 0.1
    coarse_modes: int = 0
    modes: int = 20
    initial_modes: int = 1
    stall_start: float = 1.4e-3
    stall_end: float = 1.4e-5
    max_iterations_per_stage: int = 60
    max_iterations: int = 1500
    max_step: float = 2e-2
    armijo: float = 1e-4
    backtrack: float = 0.5
    max_backtracks: int = 12
    optimizer: Optimizer = "lm"
    lm_damping: float = 1e-3
    lm_max_step: float = 0.1
    lm_iterations_per_stage: int = 3
    lm_final_iterations: int | None = None
    lm_stall_decrease: float = 0.01
    preconditioner: Preconditioner = "block"
    source_sign: SourceSign = "auto"
    occupancy_samples: int = 1
    seed: int = 0
    memory_limit_gb: float | None = 8.0
    target_backend: TargetBackend = "dense"
    target_sign: SignMethod = "winding"
    point_sdf: PointSDFMethod = "poisson"
    vdb_half_width: float = 3.0
    landmark_weight: float = 1.0
    initialization: Initialization = "rigid"
    init_grid: int = 32
    init_candidates: int = 6
    init_switch: float = 0.6
    init_keep_rest: bool = True
    select_energy_factor: float = 10.0
    start_check_modes: int = 4
    start_merge_distance: float = 0.005
    start_strain_ratio: float = 2.0
    start_choice_modes: int | None = 20
    init_lm_iterations_per_stage: int = 3
    coarse_starts: bool = True
    overlap_field: bool = True
    isometry_weight: float = 3e-4
    isometry_tolerance: float = 0.2
    warped_pass: bool = True
    field_only: bool = False
    warped_band_cells: float = 2.0
    warped_iterations_per_stage: int = 3
    warped_polish_iterations: int = 30
    warped_candidates: bool = True
    warped_choice: WarpedChoice = "field"
    warped_candidate_ratio: float = 0.95
    warped_refine: int = 1
    warped_prune_modes: int = 8
    warped_prune_ratio: float = 2.0
    warped_hops: int = 1
    warped_hop_iterations: int = 20
    warped_hop_ratio: float = 0.99
    warped_descriptors: bool = True
    warped_descriptor_weight: float = 0.004
    two_way: bool = False
    two_way_iterations: int = 30
    two_way_grid: int | None = None

    @classmethod
    def paper_faithful(cls) -> "RegistrationOptions":
        """The ``"paper"`` preset: Algorithm 1's gradient descent on the full grid from the
        rest pose (no initialization, one run, no warped rest field), Eq. (3) alone (no
        isometry prior), 20 modes."""
        return cls.preset("paper")

    @classmethod
    def fast(cls) -> "RegistrationOptions":
        """The ``"fast"`` preset: the defaults on a grid of 48 on the band quadrature, without
        the warped pass's starts from other orientations. ``fast().replace(grid=g)`` for a
        grid study."""
        return cls.preset("fast")

    @classmethod
    def fastest(cls) -> "RegistrationOptions":
        """The ``"fastest"`` preset: the warped rest field alone from the starts (no run of
        Algorithm 1 on Eq. 3), its result of lowest field energy refined on Eq. (3) on the
        band quadrature; no other orientations, no hops."""
        return cls.preset("fastest")

    @classmethod
    def preset(cls, name: Preset) -> "RegistrationOptions":
        """The options of a named preset, read from ``morphmodes_vol/presets/<name>.toml``
        (its ``[options]`` table changes the defaults); ``replace`` then changes any field.

        Examples
        --------
        >>> RegistrationOptions.preset("fast") == RegistrationOptions.fast()
        True
        >>> RegistrationOptions.preset("fast").grid
        48
        """
        return cls(**preset_table(name))

    @classmethod
    def from_table(cls, table: typing.Mapping[str, object]) -> "RegistrationOptions":
        """Options from a table of settings, as a pipeline's ``[options]``, a ``--config`` file
        or ``--set`` give them: an optional ``preset`` name, then any fields that change it.

        Raises
        ------
        OptionError
            For an unknown preset, an unknown field or an invalid value.

        Examples
        --------
        >>> RegistrationOptions.from_table({"preset": "fast", "grid": 40}).grid
        40
        """
        table = dict(table)
        base = preset_table(table.pop("preset", "default"))
        return cls().replace(**{**base, **table})

    def __post_init__(self) -> None:
        def need(cond: bool, name: str, what: str) -> None:
            if not cond:
                raise OptionError(
                    f"option {name}={getattr(self, name)!r} is invalid: expected {what}"
                )

        for name in ("padding", "stall_start", "stall_end", "max_step", "armijo", "backtrack",
                     "vdb_half_width", "lm_damping", "lm_max_step", "lm_stall_decrease",
                     "band_cells", "band_margin_cells", "landmark_weight", "isometry_weight",
                     "isometry_tolerance", "warped_band_cells"):
            need(_is_real(getattr(self, name)), name, "a finite number")
        need(self.memory_limit_gb is None or (_is_real(self.memory_limit_gb) and self.memory_limit_gb > 0),
             "memory_limit_gb", "None or a positive number of GB")
        need(_is_int(self.grid) and 4 <= self.grid <= 1024, "grid", "an integer in [4, 1024]")
        need(
            self.target_grid is None or (_is_int(self.target_grid) and 4 <= self.target_grid <= 1024),
            "target_grid",
            "None or an integer in [4, 1024]",
        )
        need(self.quadrature in QUADRATURES, "quadrature", f"one of {QUADRATURES}")
        need(self.band_cells > 0, "band_cells", "a positive float")
        need(_is_int(self.block_factor) and 1 <= self.block_factor <= 16, "block_factor",
             "an integer in [1, 16]")
        need(self.band_margin_cells > 0, "band_margin_cells", "a positive float")
        need(0.0 <= self.padding <= 2.0, "padding", "a float in [0, 2]")
        need(_is_int(self.modes) and 1 <= self.modes <= 500, "modes", "an integer in [1, 500]")
        need(_is_int(self.initial_modes) and 1 <= self.initial_modes <= self.modes,
             "initial_modes", f"an integer in [1, modes={self.modes}]")
        need(self.stall_start > 0, "stall_start", "a positive float")
        need(0 < self.stall_end <= self.stall_start, "stall_end", "a float in (0, stall_start]")
        need(_is_int(self.max_iterations_per_stage) and self.max_iterations_per_stage >= 1,
             "max_iterations_per_stage", "a positive integer")
        need(_is_int(self.max_iterations) and self.max_iterations >= 1, "max_iterations",
             "a positive integer")
        need(self.max_step > 0, "max_step", "a positive float")
        need(0 < self.armijo < 1, "armijo", "a float in (0, 1)")
        need(0 < self.backtrack < 1, "backtrack", "a float in (0, 1)")
        need(_is_int(self.max_backtracks) and self.max_backtracks >= 1, "max_backtracks",
             "a positive integer")
        need(self.optimizer in OPTIMIZERS, "optimizer", f"one of {OPTIMIZERS}")
        need(self.lm_damping > 0, "lm_damping", "a positive float")
        need(self.lm_max_step > 0, "lm_max_step", "a positive float")
        need(_is_int(self.lm_iterations_per_stage) and self.lm_iterations_per_stage >= 1,
             "lm_iterations_per_stage", "a positive integer")
        need(self.lm_final_iterations is None
             or (_is_int(self.lm_final_iterations) and self.lm_final_iterations >= 1),
             "lm_final_iterations", "None or a positive integer")
        need(0 <= self.lm_stall_decrease < 1, "lm_stall_decrease", "a float in [0, 1)")
        need(self.preconditioner in PRECONDITIONERS, "preconditioner",
             f"one of {PRECONDITIONERS}")
        need(self.source_sign in SOURCE_SIGNS, "source_sign", f"one of {SOURCE_SIGNS}")
        need(_is_int(self.occupancy_samples) and self.occupancy_samples >= 1
             and self.occupancy_samples % 2 == 1, "occupancy_samples", "a positive odd integer")
        need(_is_int(self.seed) and self.seed >= 0, "seed", "a non-negative integer")
        need(self.target_backend in TARGET_BACKENDS, "target_backend", f"one of {TARGET_BACKENDS}")
        need(self.target_sign in SIGN_METHODS, "target_sign", f"one of {SIGN_METHODS}")
        need(self.point_sdf in POINT_SDF_METHODS, "point_sdf", f"one of {POINT_SDF_METHODS}")
        need(1.0 <= self.vdb_half_width <= 64.0, "vdb_half_width", "a float in [1, 64]")
        need(self.landmark_weight >= 0, "landmark_weight", "a non-negative float")
        need(self.isometry_weight >= 0, "isometry_weight", "a non-negative float")
        need(self.isometry_tolerance >= 0, "isometry_tolerance", "a non-negative float")
        need(self.initialization in INITIALIZATIONS, "initialization", f"one of {INITIALIZATIONS}")
        need(_is_int(self.init_grid) and 8 <= self.init_grid <= 256, "init_grid", "an integer in [8, 256]")
        need(_is_int(self.init_candidates) and 1 <= self.init_candidates <= 29, "init_candidates",
             "an integer in [1, 29]")
        need(_is_real(self.init_switch) and 0 <= self.init_switch <= 1, "init_switch", "a float in [0, 1]")
        need(isinstance(self.init_keep_rest, bool), "init_keep_rest", "True or False")
        need(isinstance(self.coarse_starts, bool), "coarse_starts", "True or False")
        need(isinstance(self.overlap_field, bool), "overlap_field", "True or False")
        need(isinstance(self.warped_pass, bool), "warped_pass", "True or False")
        need(isinstance(self.field_only, bool), "field_only", "True or False")
        need(self.warped_pass or not self.field_only, "field_only",
             "False without warped_pass (the warped rest field is what field_only minimizes)")
        need(self.warped_band_cells > 0, "warped_band_cells", "a positive float")
        need(_is_int(self.warped_iterations_per_stage) and self.warped_iterations_per_stage >= 1,
             "warped_iterations_per_stage", "a positive integer")
        need(_is_int(self.warped_polish_iterations) and self.warped_polish_iterations >= 1,
             "warped_polish_iterations", "a positive integer")
        need(isinstance(self.warped_candidates, bool), "warped_candidates", "True or False")
        need(_is_real(self.warped_candidate_ratio) and 0 < self.warped_candidate_ratio <= 1,
             "warped_candidate_ratio", "a float in (0, 1]")
        need(self.warped_choice in WARPED_CHOICES, "warped_choice", f"one of {WARPED_CHOICES}")
        need(_is_int(self.warped_refine) and self.warped_refine >= 1, "warped_refine", "a positive integer")
        need(_is_int(self.warped_prune_modes) and self.warped_prune_modes >= 0, "warped_prune_modes",
             "a non-negative integer (0: off)")
        need(_is_real(self.warped_prune_ratio) and self.warped_prune_ratio >= 1, "warped_prune_ratio",
             "a float of at least 1")
        need(_is_int(self.warped_hops) and self.warped_hops >= 0, "warped_hops", "a non-negative integer (0: off)")
        need(_is_int(self.warped_hop_iterations) and self.warped_hop_iterations >= 1, "warped_hop_iterations",
             "a positive integer")
        need(_is_real(self.warped_hop_ratio) and 0 < self.warped_hop_ratio <= 1, "warped_hop_ratio",
             "a float in (0, 1]")
        need(isinstance(self.warped_descriptors, bool), "warped_descriptors", "True or False")
        need(_is_real(self.warped_descriptor_weight) and self.warped_descriptor_weight >= 0,
             "warped_descriptor_weight", "a non-negative float")
        need(isinstance(self.two_way, bool), "two_way", "True or False")
        need(_is_int(self.two_way_iterations) and self.two_way_iterations >= 1, "two_way_iterations",
             "a positive integer")
        need(self.two_way_grid is None or (_is_int(self.two_way_grid) and 4 <= self.two_way_grid <= 1024),
             "two_way_grid", "None or an integer in [4, 1024]")
        need(_is_int(self.coarse_modes) and self.coarse_modes >= 0, "coarse_modes", "a non-negative integer")
        need(_is_int(self.init_lm_iterations_per_stage) and self.init_lm_iterations_per_stage >= 1,
             "init_lm_iterations_per_stage", "a positive integer")
        need(_is_real(self.select_energy_factor) and self.select_energy_factor >= 1,
             "select_energy_factor", "a finite number >= 1")
        need(_is_int(self.start_check_modes) and self.start_check_modes >= 1, "start_check_modes",
             "a positive integer")
        need(_is_real(self.start_merge_distance) and self.start_merge_distance >= 0,
             "start_merge_distance", "a finite non-negative float")
        need(isinstance(self.start_strain_ratio, (int, float)) and not isinstance(self.start_strain_ratio, bool)
             and self.start_strain_ratio >= 1,
             "start_strain_ratio", "a float >= 1 (inf: never)")
        need(self.start_choice_modes is None or (_is_int(self.start_choice_modes) and self.start_choice_modes >= 1),
             "start_choice_modes", "a positive integer or None")

    @property
    def resolved_target_grid(self) -> int:
        """Target-grid resolution, ``grid`` when ``target_grid`` is ``None``."""
        return self.grid if self.target_grid is None else self.target_grid

    def stall_threshold(self, stage: int) -> float:
        """``eps_stall`` of Algorithm 1 for stage ``stage`` (0-based: stage s has s+1 modes).

        Decays geometrically from ``stall_start`` (first stage) to ``stall_end`` (stage
        ``modes - 1``).
        """
        if self.modes == 1:
            return self.stall_start
        t = min(max(stage, 0), self.modes - 1) / (self.modes - 1)
        return self.stall_start * (self.stall_end / self.stall_start) ** t

    def replace(self, **changes) -> "RegistrationOptions":
        """Copy with some fields changed (validated again)."""
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise OptionError(
                f"unknown option(s) {sorted(unknown)}; valid options are "
                f"{[f.name for f in dataclasses.fields(self)]}"
            )
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """Plain dictionary of the fields (for reports)."""
        return dataclasses.asdict(self)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_real(value) -> bool:
    """A finite int or float (not a bool, a string or NaN)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def preset_table(name: str) -> dict:
    """The ``[options]`` table of the preset ``name`` (a TOML file shipped in
    ``morphmodes_vol/presets``)."""
    return dict(_preset_file(name).get("options", {}))


def preset_description(name: str) -> str:
    """One line on what the preset ``name`` is for (its file's ``description``)."""
    return _preset_file(name).get("description", "")


def _preset_file(name: str) -> dict:
    if name not in PRESETS:
        raise OptionError(f"preset {name!r} is unknown: expected one of {PRESETS}")
    return toml_loads(resources.files(__package__).joinpath("presets", f"{name}.toml").read_text())


def parse_setting(item: str) -> tuple[str, object]:
    """``"key=value"`` -> ``(key, value)``, the value read as a TOML value (``48``, ``0.5``,
    ``true``, ``"band"``), else kept as the string (``band``).

    Examples
    --------
    >>> parse_setting("grid=48"), parse_setting("quadrature=band"), parse_setting("warped_pass=false")
    (('grid', 48), ('quadrature', 'band'), ('warped_pass', False))
    """
    key, sep, value = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise OptionError(f"{item!r}: expected KEY=VALUE, e.g. grid=48")
    try:
        return key, toml_loads(f"v = {value.strip()}")["v"]
    except Exception:  # not a TOML value: a bare string
        return key, value.strip()


def toml_loads(text: str) -> dict:
    """Parse TOML text (``tomllib``, or ``tomli`` on Python 3.10)."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    return tomllib.loads(text)
