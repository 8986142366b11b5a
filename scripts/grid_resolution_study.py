"""Grid-resolution study of the target SDF: both backends, several resolutions, lion pairs.

    .venv-vdb/bin/python scripts/grid_resolution_study.py [--poses 01] \\
        [--resolutions 32 48 64 96 128] [--backends dense vdb] [--set grid=48 max_iterations=300] \\
        [--memory-resolutions 64 128 256 512] [--out docs/grid_resolution_study]

For every pose, backend and resolution it registers lion-reference onto lion-<pose> with
``target_grid`` (dense: nodes along the longest side of the padded box; vdb: the same
spacing as voxel size) set to the resolution, everything else from ``--set`` on top of the
defaults, each run in a fresh subprocess so its peak memory (``ru_maxrss``) is its own. It
records the ground-truth error (shared/data README), wall time, target-SDF time (build +
sampling at the quadrature points), the target SDF's memory and the process's peak RSS.
It also measures the memory of each backend's target SDF alone at ``--memory-resolutions``
(dense: ``8 * nodes`` bytes, analytic; vdb: OpenVDB's ``memUsage`` plus the far-field mesh,
measured), and the dense-vs-vdb difference of the registered vertices at each resolution.

Writes ``study.csv``, ``memory.csv``, ``error_vs_resolution.png``, ``time_vs_resolution.png``,
``memory_vs_resolution.png`` and ``study.md`` (the tables) to ``--out``. The vdb backend needs
the OpenVDB environment (``bash dev.sh vdb-env``); run the whole study there so both backends
share one NumPy. Plots need matplotlib (the ``plots`` extra).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _data import ROOT, data_dir, parse_overrides, write_csv  # noqa: E402

import morphmodes_vol as mm  # noqa: E402
from morphmodes_vol.mesh import as_mesh, bbox_diagonal, joint_normalization  # noqa: E402
from morphmodes_vol.sdf import Grid, build_target_sdf  # noqa: E402

FIELDS = ["pose", "backend", "resolution", "voxel_size", "identity_error", "error", "modes",
          "evaluations", "status", "wall_s", "target_sdf_s", "target_sdf_mb", "peak_rss_mb",
          "dense_vs_vdb_mean", "dense_vs_vdb_max"]


def _one(args) -> int:
    """Child mode: one registration, a JSON line on stdout, the vertices in ``--vertices``."""
    data = data_dir()
    src = data / "lion-poses" / "lion-reference.obj"
    tgt = data / "lion-poses" / f"lion-{args.pose}.obj"
    options = mm.RegistrationOptions().replace(
        target_backend=args.backend, target_grid=args.resolution, **parse_overrides(args.set))
    t = time.perf_counter()
    reg = mm.Registration(src, tgt, options)
    r = reg.run(ground_truth=tgt)
    wall = time.perf_counter() - t
    np.save(args.vertices, r.vertices)
    print(json.dumps({
        "pose": args.pose, "backend": args.backend, "resolution": args.resolution,
        "voxel_size": reg.target_grid.spacing,
        "identity_error": r.metrics["identity_error"], "error": r.metrics["ground_truth_error"],
        "modes": r.modes, "evaluations": r.evaluations, "status": r.status, "wall_s": wall,
        "target_sdf_s": r.timings["target_sdf"], "target_sdf_mb": r.metrics["target_sdf_bytes"] / 1e6,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }))
    return 0


def _memory(resolutions, backends) -> list[dict]:
    """Target-SDF memory of lion-reference -> lion-01's box at each resolution."""
    data = data_dir()
    src = data / "lion-poses" / "lion-reference.obj"
    tgt = data / "lion-poses" / "lion-01.obj"
    rows = []
    for res in resolutions:
        # the normalized target and its grid exactly as a registration builds them
        V, F = as_mesh(tgt)
        Vs, _ = as_mesh(src)
        norm = joint_normalization(Vs, V)
        X0, Y = norm.apply(Vs), norm.apply(V)
        lo, hi = np.minimum(X0.min(0), Y.min(0)), np.maximum(X0.max(0), Y.max(0))
        pad = mm.RegistrationOptions().padding * float(np.linalg.norm(hi - lo))
        grid = Grid.covering(lo, hi, res, pad)
        row = {"resolution": res, "voxel_size": grid.spacing, "dense_nodes": grid.size,
               "dense_mb": 8 * grid.size / 1e6, "dense_float32_mb": 4 * grid.size / 1e6}
        if "vdb" in backends:
            t = time.perf_counter()
            sdf = build_target_sdf(Y, F, grid, "vdb")
            row.update(vdb_mb=sdf.nbytes / 1e6, vdb_tree_mb=sdf.grid.memUsage() / 1e6,
                       vdb_active_voxels=sdf.grid.activeVoxelCount(),
                       vdb_build_s=time.perf_counter() - t)
            del sdf
        rows.append(row)
        print(f"memory at {res}: {row}", file=sys.stderr, flush=True)
    return rows


def _write_csv(path: Path, rows: list[dict]) -> None:
    write_csv(path, rows)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def _markdown(rows: list[dict], keys: list[str]) -> str:
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(_fmt(r.get(k)) for k in keys) + " |" for r in rows]
    return "\n".join(lines)


def _plots(out: Path, rows: list[dict], mem: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for key, label, name in [("error", "ground-truth error", "error_vs_resolution.png"),
                             ("wall_s", "wall time (s)", "time_vs_resolution.png")]:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        for pose in sorted({r["pose"] for r in rows}):
            for backend in ("dense", "vdb"):
                sel = [r for r in rows if r["pose"] == pose and r["backend"] == backend]
                if sel:
                    ax.plot([r["resolution"] for r in sel], [r[key] for r in sel], "o-",
                            label=f"lion-{pose} {backend}")
                    if key == "wall_s":
                        ax.plot([r["resolution"] for r in sel], [r["target_sdf_s"] for r in sel],
                                "x--", label=f"lion-{pose} {backend}: target SDF only")
        ax.set_xlabel("target-SDF resolution (nodes along the longest side)")
        ax.set_ylabel(label)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / name, dpi=120)
        plt.close(fig)
    if mem:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        res = [m["resolution"] for m in mem]
        ax.loglog(res, [m["dense_mb"] for m in mem], "o-", label="dense float64 (analytic)")
        if "vdb_mb" in mem[0]:
            ax.loglog(res, [m["vdb_mb"] for m in mem], "s-", label="vdb (measured)")
        ax.set_xlabel("resolution")
        ax.set_ylabel("target SDF memory (MB)")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / "memory_vs_resolution.png", dpi=120)
        plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", nargs="*", default=["01"])
    ap.add_argument("--resolutions", nargs="*", type=int, default=[32, 48, 64, 96, 128])
    ap.add_argument("--backends", nargs="*", default=["dense", "vdb"], choices=["dense", "vdb"])
    ap.add_argument("--memory-resolutions", nargs="*", type=int, default=[64, 128, 256, 512])
    ap.add_argument("--set", nargs="*", default=[], metavar="OPTION=VALUE",
                    help="override RegistrationOptions fields, e.g. --set grid=48 max_iterations=300")
    ap.add_argument("--out", default=str(ROOT / "docs" / "grid_resolution_study"))
    # child mode
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--pose", help=argparse.SUPPRESS)
    ap.add_argument("--backend", help=argparse.SUPPRESS)
    ap.add_argument("--resolution", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--vertices", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if data_dir() is None:
        print("shared data not found (set MORPHMODES_DATA)", file=sys.stderr)
        return 1
    if args.one:
        return _one(args)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for pose in args.poses:
        verts = {}
        for res in args.resolutions:
            for backend in args.backends:
                vfile = out / f".vertices-{pose}-{backend}-{res}.npy"
                cmd = [sys.executable, __file__, "--one", "--pose", pose, "--backend", backend,
                       "--resolution", str(res), "--vertices", str(vfile), "--set", *args.set]
                print(" ".join(cmd), file=sys.stderr, flush=True)
                proc = subprocess.run(cmd, capture_output=True, text=True)
                if proc.returncode != 0:
                    print(proc.stderr, file=sys.stderr)
                    return proc.returncode
                row = json.loads(proc.stdout.strip().splitlines()[-1])
                verts[backend, res] = np.load(vfile)
                vfile.unlink()
                if backend == "vdb" and ("dense", res) in verts:
                    truth_diag = bbox_diagonal(as_mesh(
                        data_dir() / "lion-poses" / f"lion-{pose}.obj")[0])
                    d = np.linalg.norm(verts["dense", res] - verts["vdb", res], axis=1) / truth_diag
                    row.update(dense_vs_vdb_mean=float(d.mean()), dense_vs_vdb_max=float(d.max()))
                rows.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
    _write_csv(out / "study.csv", rows)
    mem = _memory(args.memory_resolutions, args.backends)
    _write_csv(out / "memory.csv", mem)
    _plots(out, rows, mem)
    command = " ".join([Path(sys.executable).name, "scripts/grid_resolution_study.py", *sys.argv[1:]])
    text = [f"Command: `{command}`", "", "Registrations (errors: fraction of the pose's bounding-box "
            "diagonal; dense_vs_vdb: mean/max vertex distance between the two backends' results, "
            "same fraction):", "", _markdown(rows, FIELDS), "", "Target-SDF memory (MB):", "",
            _markdown(mem, list(dict.fromkeys(k for m in mem for k in m)))]
    (out / "study.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
