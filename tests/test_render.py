"""Offscreen rendering (morphmodes_vol.render) and the `render` command."""

import json

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from morphmodes_vol.cli import main  # noqa: E402
from morphmodes_vol.errors import OptionError  # noqa: E402
from morphmodes_vol.render import Panel, to_plot_frame, render_panels  # noqa: E402

PNG = b"\x89PNG\r\n\x1a\n"


def png_size(path):
    data = path.read_bytes()
    assert data[:8] == PNG
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_plot_frame_is_a_rotation_putting_up_last():
    V = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(to_plot_frame(V, 1), [[3.0, 1.0, 2.0]])  # y up: (z, x, y)
    np.testing.assert_array_equal(to_plot_frame(V, 2), V)
    for up in range(3):  # a cyclic permutation keeps handedness (det +1)
        P = to_plot_frame(np.eye(3), up)
        assert np.linalg.det(P) == pytest.approx(1.0)


def test_render_panels_sizes_and_errors(tmp_path, sphere):
    V, F = sphere
    path = render_panels([Panel(V, F, "plain"), Panel(V, F, "colored", V[:, 0] ** 2)], tmp_path / "a.png",
                         panel_size=2.0, dpi=50)
    w, h = png_size(path)
    assert w == int(round((2 * 2.0 + 1.0) * 50)) and h == int(round((2.0 + 0.3) * 50))
    path = render_panels([Panel(V, F, str(k)) for k in range(3)], tmp_path / "b.png", columns=2,
                         panel_size=1.0, dpi=50)
    assert png_size(path) == (100, int(round(2.3 * 50)))  # 2 rows, no colorbar
    with pytest.raises(OptionError):
        render_panels([Panel(V, F)], tmp_path / "c.png", up="w")
    with pytest.raises(OptionError):
        render_panels([], tmp_path / "c.png")


def test_render_command_on_a_result_folder(tmp_path, small_capsule, capsys):
    import trimesh

    V, F = small_capsule
    src, tgt = tmp_path / "s.ply", tmp_path / "t.ply"
    trimesh.Trimesh(V, F, process=False).export(src)
    trimesh.Trimesh(V * [1.1, 1, 1], F, process=False).export(tgt)
    out = tmp_path / "res"
    assert main(["register", str(src), str(tgt), "-o", str(out), "--grid", "12", "--modes", "1",
                 "--set", "max_iterations=3", "--ground-truth", str(tgt), "-q"]) == 0
    assert json.loads((out / "report.json").read_text())["inputs"]["ground_truth"] == str(tgt)
    png = tmp_path / "r.png"
    assert main(["render", str(out), str(src), "-o", str(png), "--with-inputs"]) == 0
    # source, target, the result (colored by its report's ground truth), the plain mesh file
    assert "4 panels, 1 colored" in capsys.readouterr().out
    assert png_size(png)[0] > 0
    # a folder that is not a result, and a ground truth of another size: one line, exit 2
    assert main(["render", str(tmp_path), "-o", str(png)]) == 2
    assert main(["render", str(src), "--ground-truth", str(tmp_path / "res" / "registered.ply"), "-o", str(png)]) == 0
    other = tmp_path / "o.ply"
    trimesh.creation.icosphere(1).export(other)
    assert main(["render", str(src), "--ground-truth", str(other), "-o", str(png)]) == 2
    assert "same vertex count" in capsys.readouterr().err
