"""Where the objective lies at the ground truth: an energy failure or a search failure?

For a pair of ``../shared/data`` (reference -> pose) and a target kind (a scan kind of
``scan_study.py`` or a variant of ``robustness_study.py``), the objective of the defaults
(Eq. 3 on every grid node, weighted by an open target's confidence, plus the isometry prior)
is evaluated at the ground truth (the pose's own vertices: the source's vertices moved to
where they belong). Eq. (3)'s part is split by where the nodes lie relative to the target:
in front of it (the cosine between ``q - p`` and the normal of the closest target triangle
above 0.2), beside it (within +-0.2) or behind it, near it (``|g|`` within the band of
``confidence_band_cells`` spacings) or far; with the share where the truth is farther from the node
than the target (``f > g``); for a point cloud, also the share where the closest point of the
target's surface lies farther than 2% of the diagonal from every point: surface the
reconstruction invented. With ``--register``, the registration is run too and its
objective printed beside the truth's: a result whose objective is lower than the truth's
means the energy prefers the wrong shape to the true one. (The truth is taken as it is, not
refined in the subspace: a refinement from it may still find a shape near it below the
result, which would make the failure the search's.)

    python scripts/truth_energy.py cat-04 partial
    python scripts/truth_energy.py chicken-05 view1-points --register [--set isometry_weight=0]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import mesh_file, parse_overrides  # noqa: E402
from scan_study import KINDS, scan_target  # noqa: E402

import morphmodes_vol as mm  # noqa: E402
from morphmodes_vol.mesh import load_mesh  # noqa: E402
from morphmodes_vol.metrics import ground_truth_error  # noqa: E402
from morphmodes_vol.pointcloud import PointCloud  # noqa: E402
from morphmodes_vol.sdf.confidence import front_cosine  # noqa: E402
from morphmodes_vol.sdf.source import closest_points  # noqa: E402
from morphmodes_vol.variants import VARIANTS, target_variant  # noqa: E402

_SIDE = 0.2  # in front / beside / behind: the ends of the confidence's ramp (sdf/confidence.py)
_INVENTED = 0.02  # farther than this fraction of the diagonal from every point: invented


def regions(reg: mm.Registration, cp) -> dict[str, np.ndarray]:
    """Boolean masks ``(N,)`` over the grid nodes of ``reg``: in front / beside / behind
    its target, near (within the band) or far; ``cp`` the nodes' closest points on the
    target's surface."""
    cosine = front_cosine(reg.Y, reg.target_sdf_faces, reg.Q, cp)
    near = np.abs(reg.g) < reg.options.confidence_band_cells * reg.quadrature.spacing
    out = {}
    for side, m in (("in front", cosine > _SIDE), ("beside", np.abs(cosine) <= _SIDE), ("behind", cosine < -_SIDE)):
        out[f"{side}, near"] = m & near
        out[f"{side}, far"] = m & ~near
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pair", help="a pose of ../shared/data, e.g. cat-04")
    ap.add_argument("kind", choices=sorted(set(KINDS) | set(VARIANTS)), help="the target as delivered")
    ap.add_argument("--register", action="store_true", help="also register and compare objectives")
    ap.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE", help="override options")
    args = ap.parse_args()

    source = load_mesh(mesh_file(args.pair.rsplit("-", 1)[0] + "-reference"))
    Vt, Ft = load_mesh(mesh_file(args.pair))
    seed = int(args.pair[-2:])  # the studies' seed for this pair
    target = (target_variant(Vt, Ft, args.kind, seed=seed) if args.kind in VARIANTS
              else scan_target(Vt, Ft, args.kind, seed=seed))
    reg = mm.Registration(source, target, mm.RegistrationOptions(**parse_overrides(args.set)))
    if reg.Y is None:
        raise SystemExit("the target is an SDF: no surface to split the grid by")
    truth = reg.normalization.apply(Vt)
    sdf = reg.full_energy()
    ev = reg.with_terms(sdf).evaluate(truth)  # Eq. (3)'s residual, plus the added terms
    e = sdf.weights * ev.residual**2
    print(f"{args.pair}, {args.kind}: objective at the ground truth {ev.energy:.3e}, of which "
          f"Eq. (3) {e.sum():.3e} and the added terms (the isometry prior) {ev.extra_energy:.3e}")
    cp = closest_points(reg.Y, reg.target_sdf_faces, reg.Q)
    cloud = isinstance(target, PointCloud)
    header = "| nodes | count | share of Eq. (3) | of it where f > g |"
    if cloud:
        gap, _ = cKDTree(reg.normalization.apply(target.points)).query(cp.points)
        invented = gap > _INVENTED * np.linalg.norm(np.ptp(reg.Y, axis=0))
        header += " of it on invented surface |"
    print(header + "\n" + "|---" * (header.count("|") - 1) + "|")
    for name, m in regions(reg, cp).items():
        cells = [e[m].sum(), e[m & (ev.residual > 0)].sum()] + ([e[m & invented].sum()] if cloud else [])
        print(f"| {name} | {int(m.sum())} | " + " | ".join(f"{c / max(e.sum(), 1e-300):.3f}" for c in cells) + " |")
    if args.register:
        result = reg.run()
        X = reg.normalization.apply(result.vertices)
        print(f"registered: error {ground_truth_error(result.vertices, Vt):.4f}, objective "
              f"{reg.objective(X):.3e} (the ground truth's {ev.energy:.3e})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
