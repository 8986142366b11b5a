"""The bad-input corpus of docs/bad_inputs.md: every input either gets a documented handling
with a sane result or a clear error naming the file and the problem."""

import importlib
import logging

import numpy as np
import pytest
import trimesh

import morphmodes_vol as mm
from morphmodes_vol import MeshLoadError, MeshValidationError, OptionError
from morphmodes_vol.cli import main
from morphmodes_vol.primitives import affine, capsule, icosphere

from conftest import make_rng

FAST = dict(grid=12, modes=2, max_iterations=20)


def torus(R=1.0, r=0.35, nu=16, nv=8):
    """A closed quad torus (genus 1): ``V (nu nv, 3)``, quads ``(nu nv, 4)``."""
    u = np.arange(nu) * 2 * np.pi / nu
    v = np.arange(nv) * 2 * np.pi / nv
    U, W = np.meshgrid(u, v, indexing="ij")
    V = np.stack([(R + r * np.cos(W)) * np.cos(U), (R + r * np.cos(W)) * np.sin(U), r * np.sin(W)], -1)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    quads = np.stack([i * nv + j, (i + 1) % nu * nv + j, (i + 1) % nu * nv + (j + 1) % nv,
                      i * nv + (j + 1) % nv], -1)
    return V.reshape(-1, 3), quads.reshape(-1, 4)


def small_pair():
    V, F = capsule(count=(8, 8))
    V = V * [1.0, 0.6, 1.0]
    return V, F, V * [1.1, 1.0, 1.05] + [0.03, 0, 0]


def write(path, V, F):
    trimesh.Trimesh(V, F, process=False).export(path)
    return path


# ---------------------------------------------------------------- files that are refused

def corpus_files(tmp_path):
    """name -> (path, error type, message fragment): every file load_mesh must refuse."""
    rng = make_rng()
    files = {}

    def add(name, content, error, fragment):
        path = tmp_path / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            path.write_text(content)
        files[name] = (path, error, fragment)

    tet = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
    add("empty.obj", "", MeshLoadError, "the file is empty")
    add("text.obj", "hello, this is not a mesh\n", MeshLoadError, "not a valid OBJ mesh file")
    add("noise.ply", rng.bytes(400), MeshLoadError, "cannot be read as a mesh")
    add("noise.off", "OFF\nnot numbers\n", MeshLoadError, "cannot be read as a mesh")
    add("mesh.xyz", "0 0 0\n1 1 1\n", MeshLoadError, "unsupported file extension '.xyz'")
    add("mesh", tet + "f 1 2 3\n", MeshLoadError, "unsupported file extension '(none)'")
    add("points.obj", tet, MeshLoadError, "4 vertices but no faces (a point cloud?)")
    add("nan.obj", tet.replace("v 0 0 0", "v nan 0 0") + "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
        MeshValidationError, "1 vertices have NaN or infinite coordinates (first: vertex 0)")
    add("inf.obj", tet.replace("v 0 0 1", "v 0 0 inf") + "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
        MeshValidationError, "NaN or infinite coordinates (first: vertex 3)")
    add("range.obj", tet + "f 1 3 2\nf 1 2 9\n", MeshLoadError, "index 8 is out of bounds")
    add("range.off", "OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 1 9\n", MeshLoadError,
        "face index outside the range")
    add("three.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", MeshValidationError,
        "needs at least 4 vertices, got 3")
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(rng.random((10, 3))).export(cloud)
    files["cloud.ply"] = (cloud, MeshLoadError, "10 vertices but no faces (a point cloud?)")
    return files


CORPUS = ["empty.obj", "text.obj", "noise.ply", "noise.off", "mesh.xyz", "mesh", "points.obj",
          "nan.obj", "inf.obj", "range.obj", "range.off", "three.obj", "cloud.ply"]


@pytest.mark.parametrize("name", CORPUS)
def test_bad_file_is_refused_naming_file_and_problem(tmp_path, name):
    path, error, fragment = corpus_files(tmp_path)[name]
    with pytest.raises(error) as info:
        mm.load_mesh(path, min_vertices=4)
    message = str(info.value)
    assert str(path) in message and fragment in message
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize("name", ["empty.obj", "mesh.xyz", "nan.obj", "cloud.ply"])
@pytest.mark.parametrize("role", ["source", "target"])
def test_cli_bad_file_one_line_exit_2_no_output(tmp_path, capsys, name, role):
    bad, _, fragment = corpus_files(tmp_path)[name]
    V, F, target = small_pair()
    good = write(tmp_path / "good.obj", V, F)
    args = [str(bad), str(good)] if role == "source" else [str(good), str(bad)]
    out = tmp_path / "out"
    if role == "target" and name in ("mesh.xyz", "cloud.ply"):
        # a target may be a point cloud (Open3D reads .xyz, a .ply of vertices alone): these
        # are refused for having too few points to be a surface
        fragment = "points, fewer than the 100 a surface needs"
    assert main(["register", *args, "-o", str(out), "--grid", "12", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and fragment in err[0]
    assert "Traceback" not in err[0] and not out.exists()


def test_cli_verbose_shows_the_traceback(tmp_path):
    bad, _, _ = corpus_files(tmp_path)["empty.obj"]
    with pytest.raises(MeshLoadError):
        main(["register", str(bad), str(bad), "-o", str(tmp_path / "o"), "-v"])


# ---------------------------------------------------------------- arrays that are refused

@pytest.mark.parametrize(
    "target, fragment",
    [
        (icosphere(1)[0], "target: a set of points: no faces"),
        (trimesh.PointCloud(icosphere(1)[0]), "target: a set of points: no faces"),
        ((icosphere(1)[0], np.zeros((0, 3), int)), "target: no faces"),
        ((icosphere(1)[0][:3], [[0, 1, 2]]), "target: needs at least 4 vertices"),
    ],
)
def test_point_set_or_tiny_target_is_refused(target, fragment):
    V, F, _ = small_pair()
    with pytest.raises(MeshValidationError, match=fragment):
        mm.register((V, F), target, **FAST)


def test_source_with_three_vertices_is_refused():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    with pytest.raises(MeshValidationError, match="source: needs at least 4 vertices, got 3"):
        mm.register((V, [[0, 1, 2]]), icosphere(1), **FAST)


def test_nan_and_out_of_range_arrays_are_refused():
    V, F, target = small_pair()
    Vn = V.copy()
    Vn[5, 1] = np.inf
    with pytest.raises(MeshValidationError, match="source: 1 vertices have NaN or infinite .* vertex 5"):
        mm.register((Vn, F), (target, F), **FAST)
    with pytest.raises(MeshValidationError, match=rf"target: face indices must lie in \[0, {len(V) - 1}\]"):
        mm.register((V, F), (target, F + 1), **FAST)


# ---------------------------------------------------------------- very large inputs

def test_too_large_grid_is_refused_before_any_heavy_work(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("the eigenbasis was computed before the size check")

    # (morphmodes_vol.register is also the name of the function the package exports)
    monkeypatch.setattr(importlib.import_module("morphmodes_vol.register"), "mesh_skinning_weights", fail)
    V, F, target = small_pair()
    with pytest.raises(OptionError) as info:
        mm.register((V, F), (target, F), grid=1024)  # ~0.17e9 quadrature points
    message = str(info.value)
    assert "would need about" in message and "above the limit of 8 GB" in message
    assert "memory_limit_gb" in message and "x1024 quadrature grid" in message


def test_vertex_count_enters_the_estimate_and_the_limit_is_an_option():
    V, F = icosphere(5)  # 10242 vertices
    big = dict(grid=8, modes=40)
    with pytest.raises(OptionError, match=r"source \(10242 vertices\) .* above the limit of 0.26 GB"):
        mm.Registration((V, F), (V * 1.1, F), mm.RegistrationOptions(memory_limit_gb=0.26, **big))
    # the 10242 vertices and 40 modes account for more than 20 MB of the estimate
    from morphmodes_vol.limits import estimate_memory

    small_mesh = estimate_memory(42, 80, 80, 40, 8**3, 8**3).total
    large_mesh = estimate_memory(len(V), len(F), len(F), 40, 8**3, 8**3).total
    assert large_mesh - small_mesh > 0.02e9
    with pytest.raises(OptionError, match="memory_limit_gb"):
        mm.RegistrationOptions(memory_limit_gb=0)
    assert mm.RegistrationOptions(memory_limit_gb=None).memory_limit_gb is None


# ---------------------------------------------------------------- inputs that are handled

def test_quads_are_split_in_arrays_and_files_alike(tmp_path):
    V, Q = torus()
    Vv, F = mm.validate_mesh(V, Q, "torus")
    assert F.shape == (2 * len(Q), 3)
    np.testing.assert_array_equal(F[: len(Q)], Q[:, [0, 1, 2]])
    np.testing.assert_array_equal(F[len(Q):], Q[:, [0, 2, 3]])
    path = tmp_path / "torus.obj"
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in V] + [f"f {' '.join(str(i + 1) for i in q)}" for q in Q]
    path.write_text("\n".join(lines) + "\n")
    Vf, Ff = mm.load_mesh(path)
    np.testing.assert_allclose(Vf, V)
    assert sorted(map(tuple, np.sort(Ff, 1))) == sorted(map(tuple, np.sort(F, 1)))
    r = mm.register((V, Q), (V * [1.1, 1, 1], Q), **FAST)
    assert r.vertices.shape == V.shape and r.faces.shape == F.shape


def test_degenerate_and_duplicate_faces_do_not_change_the_sdfs():
    V, F, target = small_pair()
    zero = np.array([[0, 0, 1], [1, 2, 1]])
    dirty = np.vstack([F, F[:7], F[3:9, ::-1], zero])
    clean = mm.Registration((V, F), (target, F), mm.RegistrationOptions(**FAST))
    reg = mm.Registration((V, dirty), (target, dirty), mm.RegistrationOptions(**FAST))
    np.testing.assert_array_equal(reg.source_sdf_faces, F)
    np.testing.assert_array_equal(reg.g, clean.g)  # target SDF at the quadrature points
    e_clean, e_dirty = clean.energy().evaluate(clean.X0), reg.energy().evaluate(reg.X0)
    assert e_dirty.energy == e_clean.energy
    np.testing.assert_allclose(reg.weights, clean.weights, atol=1e-12)  # the same eigenbasis
    r = reg.run()
    assert r.faces.shape == dirty.shape  # the output keeps the faces as given
    np.testing.assert_allclose(r.vertices, clean.run().vertices, atol=1e-12)


def test_inconsistent_and_inverted_orientation_give_the_same_sdfs():
    V, F, target = small_pair()
    flip = make_rng().random(len(F)) < 0.3
    messy = F.copy()
    messy[flip] = messy[flip][:, ::-1]
    opts = mm.RegistrationOptions(source_sign="winding", **FAST)
    clean = mm.Registration((V, F), (target, F), opts)
    # without the repair, the winding-number sign would be wrong at many grid points
    from morphmodes_vol.sdf.source import inside

    truth = inside(clean.Y, F, clean.Q, "winding")
    assert truth.any() and (inside(clean.Y, messy, clean.Q, "winding") != truth).mean() > 0.03
    assert not inside(clean.Y, F[:, ::-1], clean.Q, "winding").any()  # inside out: all "outside"
    for G in (messy, F[:, ::-1]):  # patches flipped; the whole mesh inside out
        reg = mm.Registration((V, G), (target, G), opts)
        np.testing.assert_array_equal(reg.target_sdf_faces, F)
        np.testing.assert_array_equal(reg.g, clean.g)
        assert reg.energy().evaluate(reg.X0).energy == clean.energy().evaluate(clean.X0).energy


def test_bridge_triangles_are_named_in_a_warning_and_a_clean_mesh_gets_none(caplog):
    """Vertices scrambled in a file make triangles that span the surface (the face poses of
    the validation set: 30% of the area); the target's SDF would include them, so say so."""
    from morphmodes_vol.repair import bridge_faces, sdf_faces

    V, F = icosphere(4)  # median edge about 0.06 of the radius
    with caplog.at_level(logging.WARNING):
        sdf_faces(V, F, "target")
    assert "bridges" not in caplog.text
    assert not bridge_faces(V, F).any()
    W = V.copy()
    swap = np.arange(0, 2400, 80)  # 30 vertices given their antipodes' positions
    W[swap] = -V[swap]
    bridges = bridge_faces(W, F)
    spanned = np.isin(F, swap).any(axis=1)
    assert bridges.any() and not bridges[~spanned].any()  # only triangles at moved vertices
    with caplog.at_level(logging.WARNING):
        sdf_faces(W, F, "target")
    assert f"target: {int(bridges.sum())} triangles" in caplog.text and "bridges" in caplog.text


def test_an_open_patch_keeps_the_orientation_most_of_it_was_given_in():
    """A range scan of a hollow (a bowl seen from above, its triangles facing the camera):
    its signed volume about any point is negative, yet it faces the right way. Before, the
    patch was flipped whole, and the target's sign and confidence were wrong behind it."""
    from morphmodes_vol.repair import orient_faces
    from morphmodes_vol.sdf.source import is_closed

    u = np.linspace(-1, 1, 21)
    X, Y = np.meshgrid(u, u, indexing="ij")
    V = np.c_[X.ravel(), Y.ravel(), (X**2 + Y**2).ravel()]
    i = np.arange(20)[:, None] * 21 + np.arange(20)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + 21, i.ravel() + 1, i.ravel() + 22
    F = np.r_[np.c_[a, b, c], np.c_[c, b, d]]
    up = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])[:, 2]
    F[up < 0] = F[up < 0][:, ::-1]  # every triangle faces +z, the camera above the bowl
    assert not is_closed(F)
    G, k = orient_faces(V, F)
    assert k == 0 and np.array_equal(G, F)
    some = make_rng().random(len(F)) < 0.3  # a third of them reversed: mended to the rest
    messy = F.copy()
    messy[some] = messy[some][:, ::-1]
    G, k = orient_faces(V, messy)
    assert k == some.sum() and np.array_equal(G, F)
    assert np.array_equal(orient_faces(V, F[:, ::-1])[0], F[:, ::-1])  # facing down, as given


def test_a_patch_bounded_by_non_manifold_edges_is_open_and_a_closed_one_with_a_fin_closed():
    """A patch is closed when each of its edges is used by two of its own triangles, whatever
    other triangles meet there: fins glued along the rim of a cup (each rim edge used by three
    triangles) leave the cup open, kept as given (before, it was judged by its volume and
    turned inside out); a fin glued to a tetrahedron's edge leaves it closed, turned outward."""
    from morphmodes_vol.repair import orient_faces

    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tet = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # outward
    rim = np.array([[1, 2], [2, 3], [3, 1]])
    apex = np.array([[2.0, 2, 2], [-1, -1, -1], [2, -1, 2], [-1, 2, -1], [2, 2, -1], [-1, -1, 2]])
    W = np.r_[V, apex]
    fins = np.array([[e[0], e[1], 4 + 2 * i + j] for i, e in enumerate(rim) for j in range(2)])
    cup = tet[:3][:, ::-1]  # the tetrahedron's open cup, facing in
    F = np.r_[cup, fins]
    G, k = orient_faces(W, F)
    assert k == 0 and np.array_equal(G, F)
    F = np.r_[tet[:, ::-1], fins[:1]]  # inside out, a fin on one edge (used by three triangles)
    G, k = orient_faces(W, F)
    assert k == 4 and np.array_equal(G[:4], tet) and np.array_equal(G[4:], fins[:1])


def test_open_and_non_manifold_meshes_register(caplog):
    V, F, target = small_pair()
    holes = F[6:]  # three triangles removed near a pole
    with caplog.at_level(logging.WARNING):  # ray parity asked for an open source: a warning
        mm.Registration((V, holes), (target, F), mm.RegistrationOptions(source_sign="raycast", **FAST))
    assert "not closed or has non-manifold edges" in caplog.text
    # by default (auto) an open source's inside is its winding number, a closed one's ray parity
    r = mm.register((V, holes), (target, F), ground_truth=target, **FAST)
    assert r.options.source_sign == "winding"
    assert r.metrics["ground_truth_error"] < 0.5 * r.metrics["identity_error"]
    assert mm.Registration((V, F), (target, F), mm.RegistrationOptions(**FAST)).options.source_sign == "raycast"
    # an open target: its sign comes from the winding number, robust behind holes
    r = mm.register((V, F), (target, holes), ground_truth=target, **FAST)
    assert r.metrics["ground_truth_error"] < 0.5 * r.metrics["identity_error"]
    # a fin: a third triangle on an edge of the closed source
    a, b = F[0, 0], F[0, 1]
    Vf = np.vstack([V, (V[a] + V[b]) / 2 + [0.3, 0, 0]])
    Ff = np.vstack([F, [[a, b, len(V)]]])
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        r = mm.register((Vf, Ff), (target, F), source_sign="raycast", **FAST)
    assert "non-manifold" in caplog.text
    assert np.isfinite(r.vertices).all() and r.history.energy[-1] < r.history.energy[0]


@pytest.mark.parametrize("scale, offset", [(1e6, 3e6), (1e-6, -2e-6)])
def test_units_do_not_matter(scale, offset):
    V, F, target = small_pair()
    unit = mm.register((V, F), (target, F), **FAST)
    scaled = mm.register((V * scale + offset, F), (target * scale + offset, F), **FAST)
    # equal up to Open3D's float32 closest-triangle search in the normalized frame
    np.testing.assert_allclose(scaled.vertices, unit.vertices * scale + offset, rtol=0,
                               atol=2e-5 * scale)
    assert np.abs(unit.vertices - V).max() > 0.02  # and the registration did move it


def test_disjoint_bounding_boxes_move_towards_the_target(caplog):
    V, F, _ = small_pair()
    far = V + [1.5, 0, 0]  # the boxes do not overlap: 0.7 of the capsule's length apart
    # the defaults (initial alignment, Levenberg-Marquardt) and one Levenberg-Marquardt run
    # from the rest pose both close most of the gap, on the band quadrature (on a grid of 32:
    # on one of 16 its 4 spacings are a quarter of the box, and the run from the rest pose
    # stretched the source out of the box, docs/decisions/0021)
    for init in ("rigid", "none"):
        r = mm.register((V, F), (far, F), ground_truth=far, grid=32, modes=2, max_iterations=40,
                        optimizer="lm", quadrature="band", initialization=init)
        assert np.isfinite(r.vertices).all()
        assert r.metrics["ground_truth_error"] < 0.5 * r.metrics["identity_error"]
    # the last runs, from the rest pose (the warped pass's choice, before any hop from it)
    assert r.metrics["warped_pass"]["kept_before_hops"] in ("rest", "warped: rest")
    # the paper's gradient steps from the rest pose only start moving (they shrink the source
    # towards nothing, and stop before turning it inside out: decision 0017), and say it may
    # have failed
    with caplog.at_level(logging.WARNING):
        r = mm.register((V, F), (far, F), ground_truth=far, grid=16, modes=2, max_iterations=40,
                        optimizer="paper", quadrature="full", initialization="none", warped_pass=False)
    assert "the registration may have failed" in caplog.text
    assert np.isfinite(r.vertices).all()
    assert r.history.energy[-1] < 0.8 * r.history.energy[0]
    assert r.metrics["ground_truth_error"] < 0.95 * r.metrics["identity_error"]


def test_different_genus_registers_both_ways():
    Vt, Qt = torus()
    Vs, Fs = icosphere(2)
    blob = Vs * [1.3, 1.3, 0.5]
    for src, tgt in (((Vt, Qt), (blob, Fs)), ((blob, Fs), (Vt * 0.9, Qt))):
        r = mm.register(src, tgt, grid=16, modes=2, max_iterations=20)
        assert np.isfinite(r.vertices).all()
        assert r.history.energy[-1] < 0.7 * r.history.energy[0]


# ---------------------------------------------------------------- degenerate eigenproblems

@pytest.mark.parametrize("subdivisions", [1, 3])  # dense (84 vertices) and sparse (1284) solvers
def test_components_are_joined_into_one_zero_mode(subdivisions):
    """Two spheres, apart: the coupling of their components leaves one zero mode (the
    constant); the next is smooth on each sphere and tells them apart (nearly constant on
    each, of opposite signs), not an arbitrary mix of their indicators."""
    from morphmodes_vol.eigenbasis import mesh_skinning_weights
    from morphmodes_vol.eigenbasis.lumped_mass import lumped_mass

    A, FA = icosphere(subdivisions)
    V = np.vstack([A * 0.4 - [0.6, 0, 0], A * 0.4 + [0.6, 0, 0]])
    F = np.vstack([FA, FA + len(A)])
    W, lam = mesh_skinning_weights(V, F, 4)
    M = lumped_mass(V, F).diagonal()
    np.testing.assert_allclose(W.T @ (M[:, None] * W), np.eye(4), atol=1e-10)
    assert lam[0] == 0 and 0 < lam[1] < 0.5 * lam[2]
    left, right = W[: len(A), 1], W[len(A):, 1]  # the second mode tells the spheres apart
    assert left.max() < 0 < right.min() or right.max() < 0 < left.min()


def test_the_modes_of_a_mesh_of_components_do_not_depend_on_a_rounding_error():
    """Identity: the modes of three overlapping ellipsoids (a symmetric arrangement of equal
    meshes, so many vertices lie at equal distances across) from copies jittered by 1e-7 of
    the diagonal agree to 1e-4, up to each mode's sign (the subspace is what registers)."""
    from morphmodes_vol.eigenbasis import mesh_skinning_weights
    from morphmodes_vol.variants import jittered

    A, FA = icosphere(2)
    V = np.vstack([A * [0.5, 0.3, 0.2] + [x, 0.1 * x * x, 0] for x in (-0.8, 0.0, 0.8)])
    F = np.vstack([FA + k * len(A) for k in range(3)])
    W0, lam0 = mesh_skinning_weights(jittered(V, 1e-7, seed=1), F, 5)
    W1, lam1 = mesh_skinning_weights(jittered(V, 1e-7, seed=2), F, 5)
    assert lam0[1] > 0 and np.all(np.diff(lam0) > 1e-2 * lam0[-1])  # no repeated eigenvalue
    W1 = W1 * np.sign(np.sum(W0 * W1, axis=0))
    np.testing.assert_allclose(W0, W1, atol=1e-4 * np.abs(W0).max())


def test_components_move_independently():
    A, FA = icosphere(1)
    V = np.vstack([A * 0.4 - [0.6, 0, 0], A * 0.4 + [0.6, 0, 0]])
    F = np.vstack([FA, FA + len(A)])
    target = V.copy()
    target[: len(A)] += [0, 0.1, 0]
    target[len(A):] += [0, -0.1, 0.05]
    r = mm.register((V, F), (target, F), grid=20, modes=2, max_iterations=60, ground_truth=target)
    assert r.metrics["ground_truth_error"] < 0.5 * r.metrics["identity_error"]


def test_tiny_speck_component_near_singular_mass():
    from morphmodes_vol.eigenbasis import mesh_skinning_weights
    from morphmodes_vol.eigenbasis.lumped_mass import lumped_mass

    V, F = icosphere(2)
    S, FS = icosphere(0)
    V2 = np.vstack([V, S * 1e-6 + [1.3, 0, 0]])  # a scanning speck: mass ratio ~1e-11
    F2 = np.vstack([F, FS + len(V)])
    W, lam = mesh_skinning_weights(V2, F2, 6)
    M = lumped_mass(V2, F2).diagonal()
    assert M[len(V):].mean() < 1e-10 * M[: len(V)].mean()
    assert np.isfinite(W).all()
    np.testing.assert_allclose(W.T @ (M[:, None] * W), np.eye(6), atol=1e-10)
    target = affine(V2, np.diag([1.1, 1.0, 0.95]), [0.02, 0, 0])
    r = mm.register((V2, F2), (target, F2), grid=16, modes=3, max_iterations=30, ground_truth=target)
    assert r.metrics["ground_truth_error"] < 0.01 * r.metrics["identity_error"] + 1e-4


def test_sliver_triangles_keep_weights_smooth():
    from morphmodes_vol.eigenbasis import mesh_skinning_weights

    V, F = icosphere(2)
    a, b, c = F[0]
    n = len(V)
    p = V[a] + 1e-10 * (V[b] + V[c] - 2 * V[a])  # a vertex 1e-10 from a corner: slivers
    V2 = np.vstack([V, p])
    F2 = np.vstack([F[1:], [[a, b, n], [b, c, n], [c, a, n]]])
    W, lam = mesh_skinning_weights(V2, F2, 6)
    assert np.isfinite(W).all() and np.isfinite(lam).all()
    assert np.abs(W[n] - W[a]).max() < 1e-6 * np.abs(W).max()


def test_cli_memory_limit_option(tmp_path, capsys):
    V, F, target = small_pair()
    src, tgt = write(tmp_path / "s.obj", V, F), write(tmp_path / "t.obj", target, F)
    assert main(["register", str(src), str(tgt), "-o", str(tmp_path / "o"), "--grid", "12",
                 "--set", "memory_limit_gb=0.01", "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{src} (66 vertices)" in err[0] and "above the limit of 0.01 GB" in err[0]


def test_eigensolver_failure_is_a_clear_error(monkeypatch):
    import scipy.sparse.linalg as spla

    def no_convergence(*args, **kwargs):
        raise spla.ArpackNoConvergence("ARPACK error -1: No convergence", np.zeros(0), np.zeros((0, 0)))

    monkeypatch.setattr(spla, "eigsh", no_convergence)
    V, F = icosphere(3)  # 642 vertices: the sparse solver
    with pytest.raises(MeshValidationError, match="source: the skinning eigenproblem could not be solved"):
        mm.register((V, F), (V * 1.1, F), grid=8, modes=2)


def test_an_open_source_registers_unsigned_onto_either_side_of_its_target():
    # a cap (an open surface: a mask, a sheet) onto a stretched copy whose triangles face
    # the other way, as a scan seen from behind delivers it: matched unsigned it lands on the
    # copy whichever way the copy faces; with the winding number's sign (the default for an
    # open source) it turns over
    V, F = icosphere(3)
    used, Fc = np.unique(F[V[F].mean(axis=1)[:, 2] > -0.2], return_inverse=True)
    Vc, Fc = V[used], Fc.reshape(-1, 3)
    target = Vc * [1.15, 1.0, 0.9] + [0.05, 0, 0]
    opts = dict(grid=16, modes=4, max_iterations=40)
    for faces in (Fc, Fc[:, ::-1]):
        r = mm.register((Vc, Fc), (target, faces), ground_truth=target, source_sign="unsigned", **opts)
        assert r.metrics["ground_truth_error"] < 0.1 * r.metrics["identity_error"]
    r = mm.register((Vc, Fc), (target, Fc[:, ::-1]), ground_truth=target, **opts)
    assert r.options.source_sign == "winding"
    assert r.metrics["ground_truth_error"] > r.metrics["identity_error"]
