"""Every tunable of a registration, as frozen dataclasses with named fields.

Units: all lengths are in the *normalized* frame, in which the union bounding box of source
and target has a diagonal of 1 (see :mod:`morphmodes_vol.mesh`). A length of ``0.01`` is
therefore 1% of the size of the scene, whatever the units of the input files.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import typing
from dataclasses import dataclass
from importlib import resources
from typing import Literal

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from .errors import OptionError
from .sdf.points import POINT_SDF_METHODS, PointSDFMethod
from .sdf.source import SignMethod
from .sdf.target import TARGET_BACKENDS, TargetBackend

__all__ = ["RegistrationOptions", "parse_setting", "preset_table", "preset_description", "read_toml",
           "Preconditioner", "PRECONDITIONERS", "SIGN_METHODS", "Optimizer", "OPTIMIZERS", "Quadrature",
           "QUADRATURES", "Initialization", "INITIALIZATIONS"]

Preconditioner = Literal["block", "none"]
PRECONDITIONERS = typing.get_args(Preconditioner)
SIGN_METHODS = typing.get_args(SignMethod)
SourceSign = Literal["auto", "raycast", "winding", "unsigned"]
SOURCE_SIGNS = typing.get_args(SourceSign)
Optimizer = Literal["lm", "paper"]
OPTIMIZERS = typing.get_args(Optimizer)
Quadrature = Literal["full", "band"]
QUADRATURES = typing.get_args(Quadrature)
Initialization = Literal["none", "rigid", "similarity"]
INITIALIZATIONS = typing.get_args(Initialization)
Preset = Literal["default", "accurate", "fast", "fastest", "paper"]
PRESETS = typing.get_args(Preset)


@dataclass(frozen=True)
class RegistrationOptions:
    """Options of :func:`morphmodes_vol.register`. Lengths are in the normalized frame (the
    union box of source and target has a diagonal of 1). docs/method.md describes the stages
    these options steer; the presets (:meth:`preset`) are tables of them.

    Attributes
    ----------
    grid : int
        Quadrature nodes along the longest side of the padded box (Eq. 3); the other sides
        get the same spacing ``h``.
    target_grid : int or None
        Nodes of the dense target-SDF grid along the longest side; ``None``: ``grid``.
    quadrature : {"full", "band"}
        ``"full"``: every grid node (Eq. 3). ``"band"``: every node within ``band_cells``
        spacings of the target's surface and one per block of ``block_factor^3`` nodes
        elsewhere, weighted by the block's volume; set by the target alone, never refreshed
        (:mod:`morphmodes_vol.quadrature`, docs/decisions/0021); an open target (a partial
        scan) keeps every node. Runs are compared on every node either way.
    band_cells : float
        Half width of the band quadrature's fine band, in spacings.
    confidence_band_cells : float
        Half width, in spacings, of the band around an open target within which its field
        is trusted on both sides (:mod:`morphmodes_vol.sdf.confidence`).
    block_factor : int
        Nodes per block side away from the target's surface (``"band"``).
    padding : float
        Margin on every side of the union bounding box, a fraction of its diagonal.
    modes : int
        ``m_max``, the most skinning eigenmodes (12 degrees of freedom each).
    initial_modes : int
        Modes active from the start: ``1`` (a global affine map) as Algorithm 1;
        ``modes`` optimizes in a fixed subspace (``baselines.fixed_subspace``).
    stall_start, stall_end : float
        ``eps_stall`` of the first and the last stage, decayed geometrically in between; the
        RMS vertex motion of one step, so the schedule does not depend on the vertex count.
    max_iterations_per_stage : int
        Gradient steps of one stage before the next mode is added anyway (``"paper"``).
    max_iterations : int
        Steps of a whole run.
    max_step : float
        RMS vertex motion of a stage's first trial gradient step, and the most of any.
    armijo : float
        Sufficient-decrease constant of both step rules.
    backtrack : float
        Step shrink factor of the line search, in (0, 1).
    max_backtracks : int
        Trial steps of one line search before the stage is declared stalled.
    optimizer : {"lm", "paper"}
        ``"lm"``: Levenberg-Marquardt on the Gauss-Newton model with frozen closest points,
        accepted on the true energy. ``"paper"``: Algorithm 1's gradient step with a
        backtracking line search (see ``preconditioner``).
    lm_damping : float
        Initial damping, relative to the scale of the normal equations; Nielsen's rule then.
    lm_max_step : float
        Largest RMS vertex motion of one Levenberg-Marquardt step.
    lm_iterations_per_stage : int
        Levenberg-Marquardt steps of one stage at most.
    lm_final_iterations : int or None
        Steps of the last stage at most; ``None``: ``lm_iterations_per_stage``.
    lm_stall_decrease : float
        A stage also ends when a step lowers the energy by less than this fraction of it.
    preconditioner : {"block", "none"}
        ``"block"`` scales each mode's block of the gradient by the inverse of its 4x4 Gram
        matrix ``[X0 1]^T diag(w_j)^2 [X0 1]`` (our deviation from the paper); ``"none"`` is
        the paper's plain step.
    source_sign : {"auto", "raycast", "winding", "unsigned"}
        Inside test of the deformed source: ray parity (exact for closed sources), the
        generalized winding number (robust to holes), or ``"auto"``: by the source's topology.
        ``"unsigned"``: no inside, both fields matched as unsigned distances, for an open
        source (a mask, a sheet) that a scan may show from either side (docs/decisions/0023).
    occupancy_samples : int
        Rays cast (odd; majority vote) by the ray-parity test.
    seed : int
        Seed of the sparse eigensolvers' start vectors.
    memory_limit_gb : float or None
        Refuse, before any heavy work, a registration whose estimated peak memory
        (:mod:`morphmodes_vol.limits`) exceeds this many GB; ``None``: no limit.
    target_backend : {"dense", "vdb"}
        Storage of the target SDF: a regular grid, or a narrow-band OpenVDB level set of the
        same voxel size (docs/target_sdf.md). A target given as an SDF file keeps its type.
    target_sign : {"winding", "raycast"}
        Inside test of the target: generalized winding number (right behind holes) or ray
        parity.
    point_sdf : {"poisson", "winding"}
        A point-cloud target's field (:mod:`morphmodes_vol.sdf.points`): its screened Poisson
        surface, trimmed where no point is near, registered onto as a mesh; or the distance to
        the nearest point's tangent disc signed by the oriented points' winding number.
    vdb_half_width : float
        Half width of the ``"vdb"`` band, in voxels.
    landmark_weight : float
        Weight of the landmarks' term: ``1`` makes the mean squared landmark miss count as
        much as the mean squared SDF residual over the box; ``0`` ignores them.
    initialization : {"rigid", "similarity", "none"}
        Alignment before Algorithm 1 (:mod:`morphmodes_vol.initialize`): the rigid motion (or
        similarity) minimizing Eq. (3) on a coarse grid from several orientations; ``"none"``
        starts at the rest pose, as the paper.
    init_grid : int
        Nodes along the longest side of the initialization's coarse grid.
    init_candidates : int
        Orientations refined: the unrotated one and the best ``init_candidates - 1`` of the
        28 screened.
    init_keep_rest : bool
        Run Algorithm 1 from the rest pose as well as from the aligned start.
    coarse_starts : bool
        Run the starts on every other node of the grid (grids of 48 nodes or more).
    select_energy_factor : float
        Of the runs' results, the least stretched (edge strain) among those whose objective
        is within this factor of the lowest is kept (at least 1).
    start_check_modes : int
        From this many modes on, a run stops when another makes it redundant (below).
    start_merge_distance : float
        Two runs closer than this RMS distance: the more stretched stops (``0``: never).
    start_strain_ratio : float
        A run stretched more than this times another of comparable objective stops
        (``inf``: never).
    start_choice_modes : int or None
        With several runs left after this many modes, the choice is made there and the
        others stop; ``None``, or ``modes`` or more: at the end.
    isometry_weight : float
        Weight of the isometry prior (:mod:`morphmodes_vol.isometry`) added to Eq. (3),
        relative to the mean squared SDF residual; ``0``: Eq. (3) alone.
    isometry_tolerance : float
        Deviation of an edge's log stretch from the mean that costs nothing.
    warped_pass : bool
        The warped pass (:mod:`morphmodes_vol.warped_pass`): the warped rest field minimized
        from the starts, its best result refined on Eq. (3), kept when its objective is lower.
    field_only : bool
        With ``warped_pass``: no runs of Algorithm 1 from the starts; the field's best
        result is refined and kept.
    overlap_field : bool
        Minimize the field (and make the descriptor channels) on a second thread beside the
        initialization and the runs: the same results, sooner on two cores.
    warped_band_cells : float
        The field's band: nodes within this many spacings of the rest surface.
    warped_iterations_per_stage : int
        Levenberg-Marquardt steps per mode on the field.
    warped_polish_iterations : int
        Levenberg-Marquardt steps on Eq. (3) refining a field result (all modes, one stage).
    warped_candidates : bool
        Also start the field from the initialization's other orientations; their field
        results are ranked with the starts' by the objective after a refinement on the
        coarse grid, and the first is refined (decision 0014).
    warped_prune_modes : int
        Every field start runs to this many modes; only those within ``warped_prune_ratio``
        of the lowest field energy go on (``0``, or ``modes`` or more: every start).
    warped_prune_ratio : float
        See ``warped_prune_modes`` (at least 1).
    warped_hops : int
        Hops from the runs' best result and from the best refined field result (decision
        0013): the field minimized with all modes, refined on Eq. (3), kept when its
        objective is lower; the next from there (``0``: none).
    warped_hop_iterations : int
        The field's steps in a hop.
    warped_descriptors : bool
        After the hops, one hop through the field with the heat kernel signatures of both
        meshes as channels (:mod:`morphmodes_vol.descriptors`); needs a target mesh.
    warped_descriptor_weight : float
        The signatures' weight against the SDF's squared residual.
    two_way : bool
        Also register the target onto the source and run from the correspondences it
        implies (:mod:`morphmodes_vol.two_way`); the lowest objective is kept. Needs a
        target mesh; 1.7-2.4x the time. On in the ``accurate`` preset.
    two_way_iterations : int
        Levenberg-Marquardt steps of each run from the reverse correspondences.
    two_way_grid : int or None
        ``grid`` of the reverse registration; ``None``: three quarters of ``grid`` (48 at 64).
    """

    grid: int = 64
    target_grid: int | None = None
    quadrature: Quadrature = "full"
    band_cells: float = 4.0
    confidence_band_cells: float = 2.0
    block_factor: int = 2
    padding: float = 0.1
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
    lm_iterations_per_stage: int = 8
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
    init_keep_rest: bool = True
    select_energy_factor: float = 10.0
    start_check_modes: int = 4
    start_merge_distance: float = 0.005
    start_strain_ratio: float = 2.0
    start_choice_modes: int | None = 20
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
    warped_prune_modes: int = 8
    warped_prune_ratio: float = 2.0
    warped_hops: int = 1
    warped_hop_iterations: int = 20
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
        return cls().replace(**preset_table(name))

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
        return cls.preset(table.pop("preset", "default")).replace(**table)

    def __post_init__(self) -> None:
        for name, (ok, what) in _CHECKS.items():
            value = getattr(self, name)
            if not ok(value):
                raise OptionError(f"option {name}={value!r} is invalid: expected {what}")
        for ok, name, what in (
            (self.initial_modes <= self.modes, "initial_modes", f"an integer in [1, modes={self.modes}]"),
            (self.stall_end <= self.stall_start, "stall_end", "a float in (0, stall_start]"),
            (self.warped_pass or not self.field_only, "field_only",
             "False without warped_pass (the warped rest field is what field_only minimizes)"),
        ):
            if not ok:
                raise OptionError(f"option {name}={getattr(self, name)!r} is invalid: expected {what}")

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


def _int(lo: int, hi: float = math.inf):
    return lambda v: _is_int(v) and lo <= v <= hi


def _real(lo: float = -math.inf, hi: float = math.inf, open_lo: bool = False, open_hi: bool = False):
    return lambda v: (_is_real(v) and (v > lo if open_lo else v >= lo) and (v < hi if open_hi else v <= hi))


def _one_of(values):
    return lambda v: v in values


def _optional(check):
    return lambda v: v is None or check(v)


_BOOL = (lambda v: isinstance(v, bool), "True or False")
_POSITIVE = (_real(0, open_lo=True), "a positive float")
_NONNEGATIVE = (_real(0), "a non-negative float")
_COUNT = (_int(1), "a positive integer")

#: each option's check and what it expects (the relations between options are checked in
#: ``RegistrationOptions.__post_init__``)
_CHECKS = {
    "grid": (_int(4, 1024), "an integer in [4, 1024]"),
    "target_grid": (_optional(_int(4, 1024)), "None or an integer in [4, 1024]"),
    "quadrature": (_one_of(QUADRATURES), f"one of {QUADRATURES}"),
    "band_cells": _POSITIVE, "confidence_band_cells": _POSITIVE,
    "block_factor": (_int(1, 16), "an integer in [1, 16]"), "padding": (_real(0, 2), "a float in [0, 2]"),
    "modes": (_int(1, 500), "an integer in [1, 500]"), "initial_modes": _COUNT,
    "stall_start": _POSITIVE, "stall_end": _POSITIVE,
    "max_iterations_per_stage": _COUNT, "max_iterations": _COUNT, "max_step": _POSITIVE,
    "armijo": (_real(0, 1, True, True), "a float in (0, 1)"),
    "backtrack": (_real(0, 1, True, True), "a float in (0, 1)"), "max_backtracks": _COUNT,
    "optimizer": (_one_of(OPTIMIZERS), f"one of {OPTIMIZERS}"),
    "lm_damping": _POSITIVE, "lm_max_step": _POSITIVE, "lm_iterations_per_stage": _COUNT,
    "lm_final_iterations": (_optional(_int(1)), "None or a positive integer"),
    "lm_stall_decrease": (_real(0, 1, open_hi=True), "a float in [0, 1)"),
    "preconditioner": (_one_of(PRECONDITIONERS), f"one of {PRECONDITIONERS}"),
    "source_sign": (_one_of(SOURCE_SIGNS), f"one of {SOURCE_SIGNS}"),
    "occupancy_samples": (lambda v: _is_int(v) and v >= 1 and v % 2 == 1, "a positive odd integer"),
    "seed": (_int(0), "a non-negative integer"),
    "memory_limit_gb": (_optional(_real(0, open_lo=True)), "None or a positive number of GB"),
    "target_backend": (_one_of(TARGET_BACKENDS), f"one of {TARGET_BACKENDS}"),
    "target_sign": (_one_of(SIGN_METHODS), f"one of {SIGN_METHODS}"),
    "point_sdf": (_one_of(POINT_SDF_METHODS), f"one of {POINT_SDF_METHODS}"),
    "vdb_half_width": (_real(1, 64), "a float in [1, 64]"), "landmark_weight": _NONNEGATIVE,
    "initialization": (_one_of(INITIALIZATIONS), f"one of {INITIALIZATIONS}"),
    "init_grid": (_int(8, 256), "an integer in [8, 256]"),
    "init_candidates": (_int(1, 29), "an integer in [1, 29]"),
    "init_keep_rest": _BOOL, "coarse_starts": _BOOL,
    "select_energy_factor": (_real(1), "a finite number >= 1"), "start_check_modes": _COUNT,
    "start_merge_distance": (_real(0), "a finite non-negative float"),
    "start_strain_ratio": (lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 1,
                           "a float >= 1 (inf: never)"),
    "start_choice_modes": (_optional(_int(1)), "a positive integer or None"),
    "isometry_weight": _NONNEGATIVE, "isometry_tolerance": _NONNEGATIVE,
    "warped_pass": _BOOL, "field_only": _BOOL, "overlap_field": _BOOL,
    "warped_band_cells": _POSITIVE, "warped_iterations_per_stage": _COUNT,
    "warped_polish_iterations": _COUNT, "warped_candidates": _BOOL,
    "warped_prune_modes": (_int(0), "a non-negative integer (0: off)"),
    "warped_prune_ratio": (_real(1), "a float of at least 1"),
    "warped_hops": (_int(0), "a non-negative integer (0: off)"), "warped_hop_iterations": _COUNT,
    "warped_descriptors": _BOOL, "warped_descriptor_weight": _NONNEGATIVE,
    "two_way": _BOOL, "two_way_iterations": _COUNT,
    "two_way_grid": (_optional(_int(4, 1024)), "None or an integer in [4, 1024]"),
}


def preset_table(name: str) -> dict:
    """The ``[options]`` table of the preset ``name`` (a TOML file shipped in
    ``morphmodes_vol/presets``)."""
    return dict(_preset_file(name).get("options", {}))


def preset_description(name: str) -> str:
    """One line on what the preset ``name`` is for (its file's ``description``)."""
    return _preset_file(name).get("description", "")


@functools.lru_cache(maxsize=None)
def _preset_file(name: str) -> dict:
    """The parsed preset file, read once (callers copy what they hand out)."""
    if name not in PRESETS:
        raise OptionError(f"preset {name!r} is unknown: expected one of {PRESETS}")
    return tomllib.loads(resources.files(__package__).joinpath("presets", f"{name}.toml").read_text("utf-8"))


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
        return key, tomllib.loads(f"v = {value.strip()}")["v"]
    except tomllib.TOMLDecodeError:  # not a TOML value: a bare string
        return key, value.strip()


def read_toml(path: str | os.PathLike, error: type[Exception] = OptionError, what: str = "file") -> dict:
    """The TOML file at ``path`` as a dict (``tomllib``, or ``tomli`` on Python 3.10).

    Raises
    ------
    error
        ``"<path>: no such <what>"`` or ``"<path>: not valid TOML (...)"``.
    """
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise error(f"{path}: no such {what}") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML ({exc})") from None
