"""Write a landmark CSV from a ground truth: ``k`` well-spread source vertices (farthest-point
sampling on the source, from vertex 0) paired with the same vertices of the ground-truth mesh.

    python scripts/landmarks_from_truth.py SOURCE TRUTH -k 6 -o landmarks.csv

For demonstrations on posed datasets (vertex i of every pose is the same body point), e.g.
lion-reference onto lion-05 in the README's "Landmarks" section.
"""

from __future__ import annotations

import argparse

import numpy as np

from morphmodes_vol.mesh import load_mesh


def farthest_points(V: np.ndarray, k: int) -> np.ndarray:
    """``k`` vertex indices of ``V (n, 3)``, each the farthest from those chosen before."""
    chosen = [0]
    dist = np.linalg.norm(V - V[0], axis=1)
    for _ in range(k - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(V - V[chosen[-1]], axis=1))
    return np.array(chosen)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("source")
    ap.add_argument("truth", help="mesh whose vertex i is where source vertex i belongs")
    ap.add_argument("-k", type=int, default=6, help="number of landmarks (default 6)")
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args()
    V, _ = load_mesh(args.source)
    T, _ = load_mesh(args.truth)
    idx = farthest_points(V, args.k)
    with open(args.output, "w") as fh:
        fh.write("source_vertex_index,x,y,z\n")
        for i in idx:
            fh.write(f"{i},{T[i, 0]:.9g},{T[i, 1]:.9g},{T[i, 2]:.9g}\n")
    print(f"{args.output}: {args.k} landmarks, source vertices {idx.tolist()}")


if __name__ == "__main__":
    main()
