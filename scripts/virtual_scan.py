"""Virtual range scans of a mesh, as a depth camera makes them (morphmodes_vol.scanner).

    python scripts/virtual_scan.py lion-01.obj -o scans/lion-01 --views 1
    python scripts/virtual_scan.py lion-01.obj -o scans/lion-01 --views 2 --mesh --noise 2e-3

Writes ``<out>/view<k>.ply`` per view (oriented points; with ``--mesh``, the range image's
mesh) and ``<out>/all.ply``, every view's points (or meshes) together. The first camera looks
from the side that sees about half of the surface (morphmodes_vol.variants.half_view_direction),
the others turned about the vertical axis by equal angles.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from morphmodes_vol.mesh import load_mesh
from morphmodes_vol.scanner import view_directions, virtual_scan
from morphmodes_vol.variants import half_view_direction


def write(path: Path, P, N, F=None) -> None:
    import open3d as o3d

    if F is None:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
        pcd.normals = o3d.utility.Vector3dVector(N)
        o3d.io.write_point_cloud(str(path), pcd)
    else:
        import trimesh

        trimesh.Trimesh(P, F, process=False).export(path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh")
    ap.add_argument("-o", "--output", required=True, help="output folder")
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--resolution", type=int, nargs=2, default=[320, 240], metavar=("W", "H"))
    ap.add_argument("--distance", type=float, default=2.0, help="camera distance, in diagonals")
    ap.add_argument("--noise", type=float, default=1e-3, help="depth noise at one diagonal, fraction of it")
    ap.add_argument("--grazing", type=float, default=0.1, help="cosine below which every hit drops out")
    ap.add_argument("--mesh", dest="as_mesh", action="store_true", help="write range-image meshes, not points")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    V, F = load_mesh(args.mesh)
    scans = virtual_scan(V, F, view_directions(args.views, half_view_direction(V, F)), tuple(args.resolution),
                         args.distance, args.noise, args.grazing, args.seed)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    for k, s in enumerate(scans):
        write(out / f"view{k}.ply", s.points, s.normals, s.faces if args.as_mesh else None)
    offsets = np.cumsum([0] + [len(s.points) for s in scans])
    P, N = np.vstack([s.points for s in scans]), np.vstack([s.normals for s in scans])
    F_all = np.vstack([s.faces + o for s, o in zip(scans, offsets)]) if args.as_mesh else None
    write(out / "all.ply", P, N, F_all)
    print(f"{len(scans)} views, {len(P)} points" + (f", {len(F_all)} triangles" if args.as_mesh else "") + f" -> {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
