"""Offscreen pictures of meshes (matplotlib, Agg backend): one panel per mesh, flat-shaded,
or colored by a per-vertex value such as the ground-truth error.

matplotlib is an optional dependency (extra ``plot``); it is imported when a picture is
drawn, with an error that says how to install it.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import OptionError

__all__ = ["Panel", "render_panels", "UP_AXES"]

log = logging.getLogger(__name__)

UP_AXES = {"x": 0, "y": 1, "z": 2}
_BASE_RGB = np.array([0.72, 0.74, 0.80])
_LIGHT = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])


@dataclass
class Panel:
    """One mesh of a picture.

    Attributes
    ----------
    vertices : (n, 3) float
    faces : (m, 3) int
    title : str
    values : (n,) float or None
        Per-vertex values to color by (e.g. :func:`morphmodes_vol.metrics.vertex_errors`);
        ``None`` draws the mesh in a neutral color.
    """

    vertices: np.ndarray
    faces: np.ndarray
    title: str = ""
    values: np.ndarray | None = None


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - depends on the environment
        raise OptionError(
            "rendering needs matplotlib: pip install 'morphmodes-vol[plot]' (or pip install matplotlib)"
        ) from None
    return plt


def to_plot_frame(V: np.ndarray, up: int) -> np.ndarray:
    """Cyclic permutation of the axes (keeps handedness) that puts axis ``up`` last, which
    matplotlib draws vertically."""
    order = [(up + 1) % 3, (up + 2) % 3, up]
    return np.asarray(V, dtype=np.float64)[:, order]


def _draw_panel(ax, panel: Panel, V: np.ndarray, color) -> None:
    """One mesh ``V (n, 3)`` (plot frame) on a 3D axis: faces shaded by a headlight, colored by
    ``color(values)`` (RGBA rows) of the panel's per-vertex values when it has them."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    F = np.asarray(panel.faces, dtype=np.int64)
    tri = V[F]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    shade = 0.35 + 0.65 * np.abs(normal @ _LIGHT)
    if panel.values is not None:
        rgb = color(np.asarray(panel.values, dtype=np.float64)[F].mean(axis=1))[:, :3]
    else:
        rgb = np.broadcast_to(_BASE_RGB, (F.shape[0], 3))
    colors = np.clip(rgb * shade[:, None], 0, 1)
    ax.add_collection3d(Poly3DCollection(tri, facecolors=colors, edgecolors="none", linewidths=0))


def render_panels(
    panels: list[Panel],
    path: str | os.PathLike,
    *,
    up: str = "y",
    elev: float = 15.0,
    azim: float = -60.0,
    vmax: float | None = None,
    colorbar_label: str = "vertex error / target diagonal",
    panel_size: float = 3.0,
    dpi: int = 90,
    columns: int | None = None,
    suptitle: str | None = None,
    zoom: float = 1.6,
) -> Path:
    """Draw ``panels`` side by side into a PNG at ``path`` (written atomically).

    All panels share one frame and scale (the union of their bounding boxes) and, when they
    carry values, one color scale from 0 to ``vmax`` (default: the largest 99th percentile).

    Parameters
    ----------
    panels : list of Panel
    path : path
        Output PNG.
    up : {"x", "y", "z"}
        The meshes' up axis (the lion and cat poses are y-up).
    elev, azim : float
        Camera elevation and azimuth in degrees (matplotlib's convention, in the frame where
        ``up`` is vertical).
    vmax : float, optional
    colorbar_label : str
    panel_size : float
        Inches per panel.
    dpi : int
    columns : int, optional
        Panels per row (default: all in one row).
    suptitle : str, optional
        A caption under the panels.
    zoom : float
        Magnification of every panel (matplotlib's 3D axes leave wide margins at 1).

    Returns
    -------
    Path

    Examples
    --------
    >>> import tempfile, os
    >>> from morphmodes_vol.primitives import icosphere
    >>> V, F = icosphere(1)
    >>> with tempfile.TemporaryDirectory() as d:
    ...     p = render_panels([Panel(V, F, "sphere", V[:, 0])], os.path.join(d, "s.png"))
    ...     p.stat().st_size > 0
    True
    """
    if up not in UP_AXES:
        raise OptionError(f"up={up!r}: expected one of {sorted(UP_AXES)}")
    if not panels:
        raise OptionError("render_panels needs at least one panel")
    plt = _pyplot()
    import matplotlib as mpl

    frames = [to_plot_frame(p.vertices, UP_AXES[up]) for p in panels]
    lo = np.min([V.min(axis=0) for V in frames], axis=0)
    hi = np.max([V.max(axis=0) for V in frames], axis=0)
    center, half = (lo + hi) / 2, (hi - lo).max() / 2  # one frame and scale for every panel
    valued = [p.values for p in panels if p.values is not None]
    if vmax is None and valued:
        vmax = max(float(np.percentile(v, 99)) for v in valued) or 1.0
    norm = mpl.colors.Normalize(vmin=0.0, vmax=vmax if vmax else 1.0)
    cmap = mpl.colormaps["viridis"]

    ncol = columns or len(panels)
    nrow = -(-len(panels) // ncol)
    fig = _figure(plt, nrow, ncol, panel_size, dpi, bool(valued), bool(suptitle))
    for k, (panel, V) in enumerate(zip(panels, frames)):
        ax = fig.add_subplot(nrow, ncol, k + 1, projection="3d")
        _draw_panel(ax, panel, V, lambda v: cmap(norm(v)))
        for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), center):
            set_lim(c - half, c + half)
        ax.set_box_aspect((1, 1, 1), zoom=zoom)
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(panel.title, fontsize=9)
    if valued:
        fig.subplots_adjust(right=1 - 1.0 / fig.get_figwidth())
        cax = fig.add_axes([1 - 0.9 / fig.get_figwidth(), 0.15, 0.15 / fig.get_figwidth(), 0.7])
        fig.colorbar(mpl.cm.ScalarMappable(norm=norm, cmap=cmap), cax=cax, label=colorbar_label)
    if suptitle:
        fig.text(0.5, 0.01, suptitle, ha="center", va="bottom", fontsize=9)  # a caption
    return _save_png(plt, fig, path, dpi)


def _figure(plt, nrow: int, ncol: int, panel_size: float, dpi: int, colorbar: bool, caption: bool):
    """An empty figure for ``nrow x ncol`` panels (and a colorbar, a caption)."""
    # whole pixels, a hair over, so that every matplotlib makes the same PNG size (some round
    # inches * dpi, others truncate it: 2.3 * 50 is 114.99999999999999)
    pixels = np.round(np.array([panel_size * ncol + (1.0 if colorbar else 0), panel_size * nrow + 0.3]) * dpi)
    fig = plt.figure(figsize=tuple((pixels + 0.01) / dpi))
    fig.subplots_adjust(left=0, right=1, bottom=0.07 if caption else 0, top=1 - 0.3 / fig.get_figheight(),
                        wspace=0, hspace=0.08)
    return fig


def _save_png(plt, fig, path, dpi: int) -> Path:
    """``fig`` as a PNG at ``path``, written atomically; the figure closed."""
    import io

    from .export import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    path = Path(path)
    atomic_write_bytes(path, buf.getvalue())
    log.info("wrote %s", path)
    return path
