"""The result is a stable function of the geometry: a source moved by a rounding error, or a
target delivered with another triangulation, registers to (about) the same place.

Generated shapes (a tapered capsule onto a stretched, bent copy: a known answer) at the defaults,
and a real-data guard over five pairs of ``../shared/data`` (two of the tuning set, three of the
validation set): the median of three jittered copies stays below 1.5 times its value measured
when the defaults were set (``scripts/robustness_study.py``), and no copy is turned inside out."""

import numpy as np
import pytest

import morphmodes_vol as mm
from morphmodes_vol.mesh import bbox_diagonal, load_mesh
from morphmodes_vol.metrics import ground_truth_error
from morphmodes_vol.primitives import bend, capsule
from morphmodes_vol.sdf import signed_volume
from morphmodes_vol.variants import jittered, partial_view, retriangulated

JITTER = 1e-7
"""The copies' jitter, relative to the source's diagonal (as the robustness study's)."""


def tapered_capsule(count=(24, 24)):
    """A capsule widening along its axis and flattened across it (no symmetry but a mirror,
    so no motion slides it along itself): ``(V (n, 3), F (m, 3))``; ``count`` as
    :func:`capsule`'s (a finer count: the same surface, another triangulation)."""
    V, F = capsule(height=1.0, radius=0.22, count=count)
    s = (V[:, 2] - V[:, 2].min()) / np.ptp(V[:, 2])
    return V * np.c_[1.0 + 0.6 * s, 0.7 + 0 * s, 1.0 + 0 * s], F


def posed(V):
    """Stretched by 1.2 along the axis, bent by 70 degrees, shifted (the demo's pose)."""
    T = bend(V * np.array([1.0, 1.0, 1.2]), np.deg2rad(70.0), axis=2, towards=0)
    return T + np.array([0.05, -0.03, 0.02])


def _register(source, target):
    return mm.register(source, target, mm.RegistrationOptions(grid=40)).vertices


def _rms(X, Y, diagonal):
    return float(np.sqrt(np.mean(np.sum((X - Y) ** 2, axis=1)))) / diagonal


@pytest.fixture(scope="module")
def pair():
    """The source, the target's vertices (vertex ``i`` is where source vertex ``i`` belongs),
    their diagonal and the registration at the defaults (grid 40)."""
    V, F = tapered_capsule()
    T = posed(V)
    return V, F, T, bbox_diagonal(T), _register((V, F), (T, F))


@pytest.mark.slow
def test_a_jittered_source_lands_where_the_source_does(pair):
    """Every vertex of the source moved by N(0, (1e-7 diagonal)^2): the registered vertices move
    by less than 1e-3 of the diagonal (RMS) and the ground-truth error by less than 5%."""
    V, F, T, diagonal, X = pair
    e = ground_truth_error(X, T)
    for seed in (1, 2):
        Xj = _register((jittered(V, JITTER, seed), F), (T, F))
        assert _rms(Xj, X, diagonal) < 1e-3, seed
        assert ground_truth_error(Xj, T) == pytest.approx(e, rel=0.05), seed


@pytest.mark.slow
def test_another_triangulation_of_the_target_gives_about_the_same_registration(pair):
    """The target's surface delivered with other triangles: a capsule of 48 x 48 segments in
    the same pose (four times the faces; the same surface up to the polygons' gap), and that
    re-meshed by quadric decimation to a quarter of its faces (about as many faces as the
    original, none of its vertices, the surface off by the decimation's error). Against the
    intact target's vertices: the finer mesh's error within 1.25x of the original's and the
    registered vertices within 1% of the diagonal (RMS); the decimated mesh's within 1.5x and
    2%."""
    V, F, T, diagonal, X = pair
    e = ground_truth_error(X, T)
    Vf, Ff = tapered_capsule(count=(48, 48))
    Tf = posed(Vf)
    for (Tt, Ft), ratio, move in [((Tf, Ff), 1.25, 0.01), (retriangulated(Tf, Ff, 0.25), 1.5, 0.02)]:
        Xt = _register((V, F), (Tt, Ft))
        assert ground_truth_error(Xt, T) <= ratio * e, (len(Ft), e, ground_truth_error(Xt, T))
        assert _rms(Xt, X, diagonal) < move, (len(Ft), _rms(Xt, X, diagonal))


@pytest.mark.slow
def test_half_a_target_registers_the_whole_source(pair):
    """Only the faces of the target seen from one side (about half; an open surface): behind
    it the target's field is a guess, which the confidence of the field leaves out of Eq. (3)
    (:mod:`morphmodes_vol.sdf.confidence`). The ground-truth error (every vertex, the unseen
    ones too) stays within 2x of the intact target's; without the confidence it was 4x."""
    V, F, T, diagonal, X = pair
    Tp, Fp = partial_view(T, F, np.array([0.0, 1.0, 0.0]))
    assert 0.3 * len(F) < len(Fp) < 0.7 * len(F)
    reg = mm.Registration((V, F), (Tp, Fp), mm.RegistrationOptions(grid=40))
    assert reg.confidence is not None
    assert ground_truth_error(reg.run().vertices, T) <= 2.0 * ground_truth_error(X, T)
    # a closed target's field is known everywhere: no weights
    assert mm.Registration((V, F), (T, F), mm.RegistrationOptions(grid=40)).confidence is None


# pair -> the median of three jittered copies at the defaults (robustness study, original
# target, `python scripts/robustness_study.py --quick --variants original`); the guard
# allows 1.5 times. dance-01: a near-symmetric body that a reflection fits (0.118, inside out,
# before decision 0017)
GUARDED = {"lion-01": 0.0125, "cat-03": 0.0379, "dance-01": 0.0094, "dance-04": 0.0029, "jump-03": 0.0140}


@pytest.mark.slow
@pytest.mark.realdata
@pytest.mark.parametrize("pair", sorted(GUARDED))
def test_real_pairs_median_of_jittered_copies_stays_below_its_measured_error(data_dir, pair):
    body = pair.rsplit("-", 1)[0]
    V, F = load_mesh(data_dir / f"{body}-poses" / f"{body}-reference.obj")
    Vt, Ft = load_mesh(data_dir / f"{body}-poses" / f"{pair}.obj")
    results = [mm.register((jittered(V, JITTER, k), F), (Vt, Ft)).vertices for k in range(3)]
    errors = [ground_truth_error(X, Vt) for X in results]
    assert np.median(errors) < 1.5 * GUARDED[pair], (pair, errors)
    # the right way out, as the source (a reflection fits a near-symmetric body's surface too)
    assert all(signed_volume(X, F) * signed_volume(V, F) > 0 for X in results), pair
