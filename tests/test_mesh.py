"""The one validator, loading without processing, joint normalization."""

import numpy as np
import pytest
import trimesh

from morphmodes_vol import MeshLoadError, MeshValidationError, as_mesh, load_mesh, validate_mesh
from morphmodes_vol.mesh import bbox_diagonal, joint_normalization
from morphmodes_vol.primitives import icosphere

TET_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def test_validate_returns_copies_with_canonical_dtypes():
    V32 = TET_V.astype(np.float32)
    F32 = TET_F.astype(np.int32)
    V, F = validate_mesh(V32, F32, "tet")
    assert V.dtype == np.float64 and F.dtype == np.int64
    V[0, 0] = 9
    assert V32[0, 0] == 0  # a copy


@pytest.mark.parametrize(
    "V, F, message",
    [
        (TET_V[:, :2], TET_F, "shape (n, 3)"),
        (np.vstack([TET_V, [[np.nan, 0, 0]]]), TET_F, "NaN or infinite"),
        (TET_V, TET_F + 1, "must lie in [0, 3]"),
        (TET_V, np.array([[0, 1, 2, 3, 0]]), "triangles (m, 3) or quads"),
        (TET_V, np.zeros((0, 3), int), "no faces"),
        (TET_V, np.array([[0.5, 1, 2]]), "integers"),
        ([["a", "b", "c"]] * 4, TET_F, "not a numeric array"),
    ],
)
def test_validate_rejects_with_clear_message(V, F, message):
    with pytest.raises(MeshValidationError, match=None) as info:
        validate_mesh(V, F, "bad.obj")
    assert message in str(info.value) and "bad.obj" in str(info.value)
    assert isinstance(info.value, ValueError)


def test_validate_min_vertices():
    with pytest.raises(MeshValidationError, match="at least 4"):
        validate_mesh(TET_V[:3], [[0, 1, 2]], "tri", min_vertices=4)


def test_load_keeps_vertex_order(tmp_path):
    V, F = icosphere(1)
    perm = np.random.default_rng(3).permutation(len(V))
    Vp = V[perm]
    Fp = np.argsort(perm)[F]
    Vdup = np.vstack([Vp, Vp[:1]])  # a duplicated, unreferenced vertex must survive
    path = tmp_path / "m.obj"
    trimesh.Trimesh(Vdup, Fp, process=False).export(path)
    V2, F2 = load_mesh(path)
    np.testing.assert_allclose(V2, Vdup, atol=1e-6)
    np.testing.assert_array_equal(F2, Fp)


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(MeshLoadError, match="no such file"):
        load_mesh(tmp_path / "missing.obj")
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    with pytest.raises(MeshLoadError, match="empty"):
        load_mesh(empty)
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(cloud)
    with pytest.raises(MeshLoadError, match="cloud.ply"):
        load_mesh(cloud)
    junk = tmp_path / "junk.xyzzy"
    junk.write_text("hello")
    with pytest.raises(MeshLoadError, match="junk.xyzzy"):
        load_mesh(junk)


def test_as_mesh_accepts_three_kinds(tmp_path):
    V, F = icosphere(1)
    path = tmp_path / "s.ply"
    trimesh.Trimesh(V, F, process=False).export(path)
    for m in (str(path), path, (V, F), trimesh.Trimesh(V, F, process=False)):
        V2, F2 = as_mesh(m)
        np.testing.assert_allclose(V2, V, atol=1e-6)
    with pytest.raises(MeshValidationError, match="expected a file path"):
        as_mesh(42)


def test_joint_normalization_is_a_similarity_undone_exactly(rng):
    A = rng.random((20, 3)) * 7 + 100
    B = rng.random((30, 3)) * 3 - 2
    nrm = joint_normalization(A, B)
    both = np.vstack([nrm.apply(A), nrm.apply(B)])
    assert bbox_diagonal(both) == pytest.approx(1.0)
    np.testing.assert_allclose((both.max(0) + both.min(0)) / 2, 0, atol=1e-12)
    np.testing.assert_allclose(nrm.undo(nrm.apply(A)), A, rtol=1e-12)
    with pytest.raises(MeshValidationError):
        joint_normalization(np.ones((4, 3)))
