"""The ``morphmodes-vol`` command line: ``register``, ``demo``, ``run``, ``sdf``, ``render``.

Errors caused by the input (a bad mesh file, an invalid option) print one line on stderr
and exit with code 2; ``-v`` shows the traceback too.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from .errors import MorphModesError, OptionError
from .export import MESH_FORMATS, check_output_path, output_names, write_outputs
from .options import PRESETS, SIGN_METHODS, RegistrationOptions, parse_setting, preset_description, read_toml
from .sdf.target import target_sdf_backend

__all__ = ["main"]


class ProgressPrinter:
    """Progress on stderr: one live line on a terminal (the run, its modes and energy),
    rewritten in place; otherwise a line when a run starts and one every ``interval``
    seconds. Details of each stage are logged under ``-v``."""

    def __init__(self, stream=None, interval: float = 5.0):
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.interval = interval
        self._last = -1e9
        self._seen: set = set()
        self._width = 0

    def __call__(self, e) -> None:
        now = time.perf_counter()
        new_run = e.start not in self._seen
        self._seen.add(e.start)
        line = ((f"[{e.start}] " if e.start else "") +
                f"modes {e.modes}/{e.max_modes}  iter {e.iteration}  energy {e.energy:.4e}  "
                f"evals {e.evaluations}  {e.elapsed:.1f}s")
        if self.tty:
            pad = max(self._width - len(line), 0)
            self.stream.write("\r" + line + " " * pad)
            self._width = len(line)
            self.stream.flush()
        elif new_run or now - self._last >= self.interval:
            self.stream.write(line + "\n")
            self.stream.flush()
            self._last = now

    def close(self) -> None:
        if self.tty and self._width:
            self.stream.write("\n")
            self.stream.flush()


def _read_config(path) -> dict:
    """The settings of a ``--config`` TOML file: the keys of :class:`RegistrationOptions` and
    ``preset``, at its top level or in an ``[options]`` table (a pipeline definition's)."""
    doc = read_toml(path, OptionError, "config file")
    table = doc.get("options", doc)
    if not isinstance(table, dict):
        raise OptionError(f"{path}: [options] must be a table")
    return {k: v for k, v in table.items() if k != "options"}


def options_from_args(args) -> RegistrationOptions:
    """The options of ``register`` and ``demo``: ``--preset`` (else the config's preset, else
    the defaults), changed by ``--config``, then ``--grid`` and ``--modes``, then each ``--set``."""
    table = _read_config(args.config) if args.config else {}
    if args.preset is not None:
        table["preset"] = args.preset
    for key, default in (("grid", args.default_grid), ("modes", args.default_modes)):
        value = getattr(args, key)
        if value is not None:
            table[key] = value
        elif default is not None and key not in table:  # the command's own (the demo's) default
            table[key] = default
    table.update(parse_setting(item) for item in args.settings)
    if table.get("memory_limit_gb") == 0:  # 0: no limit (TOML has no None)
        table["memory_limit_gb"] = None
    return RegistrationOptions.from_table(table)


def _add_common(p: argparse.ArgumentParser, default_grid: int | None, default_modes: int | None) -> None:
    d = RegistrationOptions()
    p.add_argument("--preset", choices=list(PRESETS), default=None,
                   help="a named setting: " + "; ".join(
                       f"'{name}' {preset_description(name)}" for name in PRESETS) + " (default 'default')")
    p.add_argument("--config", metavar="FILE", default=None,
                   help="TOML file of options: keys of RegistrationOptions (and 'preset') at the top "
                        "level or in an [options] table, as in a pipeline definition")
    p.add_argument("--set", action="append", default=[], dest="settings", metavar="KEY=VALUE",
                   help="change one option of RegistrationOptions, after --preset and --config "
                        "(repeatable): e.g. --set quadrature=band --set warped_hops=0 --set "
                        "memory_limit_gb=0 (no memory limit); `python -c \"import morphmodes_vol; "
                        "help(morphmodes_vol.RegistrationOptions)\"` lists them")
    p.add_argument("--grid", type=int, default=None,
                   help="quadrature points along the longest side of the box (default "
                        f"{default_grid or d.grid}, or the preset's)")
    p.add_argument("--modes", type=int, default=None,
                   help=f"maximum number of skinning eigenmodes, m_max (default {default_modes or d.modes})")
    p.set_defaults(default_grid=default_grid, default_modes=default_modes)
    p.add_argument("-v", "--verbose", action="store_true", help="log details and show tracebacks")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")


def _summary(result, paths) -> str:
    m = result.metrics
    cost = ""
    if "full_grid_equivalents" in m:
        cost = (f" + {m['comparison_evaluations']} comparisons, the cost of "
                f"{m['full_grid_equivalents']:.1f} evaluations on the full grid")
    lines = [f"status: {result.status}, {result.modes} modes, {result.evaluations} SDF evaluations{cost}, "
             f"optimize {result.timings['optimize']:.1f}s"]
    if result.status == "rolled_back":
        lines.append("a NaN or infinite energy stopped the run: the result is its last good state")
    if "init_rotation_deg" in m:
        lines.append(f"initial alignment: rotation {m['init_rotation_deg']:.1f} deg, scale "
                     f"{m['init_scale']:.3f}, {m['init_evaluations']} evaluations of the source field "
                     f"({m['init_field_nodes']} nodes), "
                     f"{result.timings['initialize']:.1f}s")
    if len(m.get("starts", [])) > 1:
        lines.append("starts: " + "; ".join(
            f"{s['start']} " + (f"stopped after {s['stopped_after_modes']} modes ({s['stop_reason']})"
                                if s["stopped_after_modes"] is not None else "ran to the end")
            for s in m["starts"]) + f"; kept: {m['start']}")
    if "warped_pass" in m:
        w = m["warped_pass"]
        lines.append("warped rest field: objective " + ", ".join(f"{k} {e:.4g}" for k, e in w["objectives"].items())
                     + f" ({w['field_evaluations']} field evaluations"
                     + (f", {len(w['field_energies'])} field starts" if len(w.get("field_energies", ())) > 3
                        else "")
                     + f"); kept: {w['kept_before_hops']}"
                     + "".join(f"; {h['start']} from the {h['from']}: objective {h['objective']:.4g}, "
                               + ("kept" if h["accepted"] else "not kept") for h in w.get("hops", ())))
    if "two_way" in m:
        t = m["two_way"]
        lines.append("two-way: objective " + ", ".join(f"{k} {e:.4g}" for k, e in t["objectives"].items())
                     + f" (reverse registration: {t['reverse_registration_evaluations']} evaluations, "
                     f"{t['reverse_registration_seconds']:.1f}s); kept: {t['kept']}")
    lines.append(f"SDF residual RMS: {m['initial_sdf_rms']:.4g} -> {m['final_sdf_rms']:.4g} "
                 "(fraction of the scene diagonal)")
    if "ground_truth_error" in m:
        lines.append(f"ground-truth error: {m['identity_error']:.4g} (identity) -> "
                     f"{m['ground_truth_error']:.4g} (registered), fraction of the target's diagonal")
    if "landmark_rms" in m:
        lines.append(f"landmark RMS distance: {m['initial_landmark_rms']:.4g} -> {m['landmark_rms']:.4g} "
                     f"(target units; {m['landmark_rms_fraction']:.4g} of the target's diagonal)")
    lines.append(f"results in {paths['report'].parent}/: " + ", ".join(p.name for p in paths.values()))
    return "\n".join(lines)


def _run(source, target, args, inputs, ground_truth=None, mesh_format="ply", landmarks=None) -> int:
    from .register import Registration

    options = options_from_args(args)
    progress = None if args.quiet else ProgressPrinter()
    reg = Registration(source, target, options, landmarks=landmarks)
    try:
        result = reg.run(progress=progress, ground_truth=ground_truth)
    finally:
        if progress is not None:
            progress.close()
    paths = write_outputs(result, args.output, inputs=inputs, mesh_format=mesh_format)
    print(_summary(result, paths))
    return 0


def cmd_register(args) -> int:
    fmt = args.format
    if fmt is None:
        ext = Path(args.source).suffix.lower().lstrip(".")
        fmt = ext if ext in MESH_FORMATS else "ply"
    check_output_path(args.output, "folder", output_names(fmt),
                      inputs=(args.source, args.target, args.ground_truth, args.landmarks))
    inputs = {"source": str(args.source), "target": str(args.target), "cli": True}
    if args.ground_truth:
        inputs["ground_truth"] = str(args.ground_truth)
    if args.landmarks:
        inputs["landmarks"] = str(args.landmarks)
    return _run(args.source, args.target, args, inputs, ground_truth=args.ground_truth, mesh_format=fmt,
                landmarks=args.landmarks)


def cmd_demo(args) -> int:
    from .demo import demo_pair

    out = check_output_path(args.output, "folder")
    (Vs, F), (Vt, Ft) = demo_pair()
    out.mkdir(parents=True, exist_ok=True)
    import trimesh

    trimesh.Trimesh(Vs, F, process=False).export(out / "source.ply")
    trimesh.Trimesh(Vt, Ft, process=False).export(out / "target.ply")
    inputs = {"source": "demo capsule (source.ply)", "target": "bent, stretched capsule (target.ply)",
              "cli": True}
    return _run((Vs, F), (Vt, Ft), args, inputs, ground_truth=Vt)


class PairProgress:
    """Pipeline progress on stderr. On a terminal: a bar over the pairs with the latest
    pair's stage, rewritten in place, and one kept line per finished pair; otherwise one line
    per state change of a pair."""

    def __init__(self, total: int, stream=None, width: int = 20):
        self.stream = stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.total = total
        self.width = width
        self.counts = {"ok": 0, "skipped": 0, "failed": 0}
        self._shown = 0

    def _head(self) -> str:
        done = sum(self.counts.values())
        if not self.tty:
            return f"[{done}/{self.total}, {self.counts['failed']} failed]"
        filled = self.width * done // max(self.total, 1)
        return f"[{'#' * filled}{'.' * (self.width - filled)}] {done}/{self.total}, {self.counts['failed']} failed"

    def event(self, name: str, text: str) -> None:
        line = f"{self._head()} {name}: {text}"
        if not self.tty:
            self.stream.write(line + "\n")
        else:
            final = text.startswith(("done", "FAILED", "skipped", "worker lost"))
            pad = " " * max(self._shown - len(line), 0)
            self.stream.write("\r" + (f"{name}: {text}" + " " * max(self._shown - len(name) - len(text) - 2, 0)
                                       + "\n" if final else line + pad))
            self._shown = 0 if final else len(line)
        self.stream.flush()

    def result(self, result: dict) -> None:
        self.counts[result["state"]] += 1
        if result["state"] == "failed" and "worker lost" in (result.get("error") or ""):
            self.event(result["name"], result["error"])

    def close(self) -> None:
        if self.tty and self._shown:
            self.stream.write("\n")
            self.stream.flush()


def _check_pipeline_outputs(pipeline) -> None:
    """The checks of :func:`check_output_path` on a pipeline's output folder, its pairs'
    folders and summaries against every input of the pipeline."""
    inputs = {p for spec in pipeline.pairs for p in (spec.source, spec.target, spec.ground_truth, spec.landmarks)
              if p is not None}
    summaries = [f"summary.{k}" for k in ("csv", "json", "md", "png")]
    check_output_path(pipeline.output, "folder", summaries, inputs)
    for spec in pipeline.pairs:
        fmt = spec.resolved_format
        check_output_path(spec.outdir, "folder", output_names(fmt) + ("failed.json",), inputs)


def cmd_run(args) -> int:
    from .pipeline import load_pipeline, run_pipeline

    pipeline = load_pipeline(args.pipeline, output=args.output)
    _check_pipeline_outputs(pipeline)
    if args.executor == "dask" and not args.verbose:
        try:  # Dask's scheduler and nannies log every connection at INFO (set before import)
            import dask

            dask.config.set({"logging.distributed": "warning"})
        except ImportError:
            pass
    progress = PairProgress(len(pipeline.pairs))
    print(f"{pipeline.name}: {len(pipeline.pairs)} pairs -> {pipeline.output} "
          f"(cache {pipeline.cache_dir}, executor {args.executor})", file=sys.stderr)
    try:
        run = run_pipeline(pipeline, args.executor, args.workers, args.scheduler,
                           on_event=None if args.quiet else progress.event, on_result=progress.result)
    finally:
        progress.close()
    print(run.paths["md"].read_text(), end="")
    counts = progress.counts
    print(f"{counts['ok']} registered, {counts['skipped']} already complete, {counts['failed']} failed "
          f"in {run.seconds:.1f}s; summary: " + ", ".join(str(p) for p in run.paths.values()))
    return 1 if run.failed else 0


def cmd_sdf(args) -> int:
    from .mesh import as_mesh, bbox_diagonal
    from .pointcloud import is_point_cloud_file
    from .targets import scan_target
    from .sdf import Grid, build_target_sdf

    out = check_output_path(args.output, "file", inputs=[args.mesh])
    backend = target_sdf_backend(out)
    opts = RegistrationOptions()
    sign = args.target_sign or opts.target_sign
    if is_point_cloud_file(args.mesh):  # a scan: the SDF of its Poisson surface
        V, F = scan_target(args.mesh, opts.replace(point_sdf="poisson", grid=args.resolution))
    else:
        V, F = as_mesh(args.mesh, "mesh")
    pad = args.padding * bbox_diagonal(V)
    grid = Grid.covering(V.min(axis=0), V.max(axis=0), args.resolution, pad)
    t = time.perf_counter()
    sdf = build_target_sdf(V, F, grid, backend, sign, args.half_width)
    seconds = time.perf_counter() - t
    sdf.save(out)
    print(f"{out}: {backend} target SDF of {args.mesh}, voxel size {grid.spacing:.4g} "
          f"(mesh frame), {sdf.nbytes / 1e6:.1f} MB in memory, {out.stat().st_size / 1e6:.1f} MB "
          f"on disk, signs by {sign}, built in {seconds:.1f}s")
    return 0


def _render_inputs(args):
    """Panels of ``render``: each INPUT is a result folder (its ``registered.*``, colored by
    the per-vertex error against ``--ground-truth`` or the report's ground truth) or a mesh."""
    import json

    from .mesh import load_mesh
    from .metrics import vertex_errors
    from .render import Panel

    truth = load_mesh(args.ground_truth)[0] if args.ground_truth else None
    panels = []
    for item in args.inputs:
        path = Path(item)
        inputs, gt = {}, truth
        if path.is_dir():
            meshes = sorted(path.glob("registered.*"))
            if not meshes or not (path / "report.json").is_file():
                raise MorphModesError(f"{path}: not a complete result folder (no registered.* or report.json)")
            inputs = json.loads((path / "report.json").read_text()).get("inputs", {})
            if gt is None and inputs.get("ground_truth") and Path(inputs["ground_truth"]).is_file():
                gt = load_mesh(inputs["ground_truth"])[0]
            if args.with_inputs:
                for key in ("source", "target"):
                    if inputs.get(key) and Path(inputs[key]).is_file():
                        panels.append(Panel(*load_mesh(inputs[key]), f"{key}: {Path(inputs[key]).stem}"))
            title, mesh = path.name, meshes[0]
        else:
            title, mesh = path.stem, path
        V, F = load_mesh(mesh)
        values = None
        if gt is not None:
            if gt.shape != V.shape:
                raise MorphModesError(f"{mesh}: {V.shape[0]} vertices, the ground truth {gt.shape[0]}: "
                                      "per-vertex error needs the same vertex count and order")
            values = vertex_errors(V, gt)
            title = f"{title} ({values.mean():.4f})"
        panels.append(Panel(V, F, title, values))
    return panels


def cmd_render(args) -> int:
    from .render import render_panels

    check_output_path(args.output, "file", inputs=[*args.inputs, args.ground_truth])
    panels = _render_inputs(args)
    path = render_panels(panels, args.output, up=args.up, elev=args.elev, azim=args.azim,
                         vmax=args.max_error, columns=args.columns)
    colored = sum(p.values is not None for p in panels)
    print(f"wrote {path} ({len(panels)} panels, {colored} colored by ground-truth error)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    d = RegistrationOptions()
    parser = argparse.ArgumentParser(
        prog="morphmodes-vol",
        description="Non-rigid registration by SDF matching in an adaptive skinning-eigenmode subspace.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("register", help="register SOURCE onto TARGET")
    p.add_argument("source", help="source mesh (OBJ, PLY, OFF, STL, ...)")
    p.add_argument("target", help="target mesh, point cloud (PLY without faces, PCD, XYZ, PTS; normals "
                                   "estimated when absent), or its SDF (.npz dense grid or .vdb level set, "
                                   "as `morphmodes-vol sdf` writes; no correspondence.npz then)")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--ground-truth", default=None,
                   help="mesh whose vertex i is where source vertex i should land (adds error metrics)")
    p.add_argument("--format", choices=MESH_FORMATS, default=None,
                   help="format of registered.* (default: the source's, else ply)")
    p.add_argument("--landmarks", default=None, metavar="CSV",
                   help="landmarks: lines 'source_vertex_index, x, y, z' (target point in the "
                        "target's frame), optional header")
    _add_common(p, None, None)
    p.set_defaults(func=cmd_register)

    p = sub.add_parser("demo", help="register the built-in capsule pair (no data needed)")
    p.add_argument("-o", "--output", default="out/demo", help="output folder (default out/demo)")
    _add_common(p, 48, 12)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("run", help="run a pipeline definition (TOML) over a dataset; exit 1 if a pair failed")
    p.add_argument("pipeline", help="pipeline definition, e.g. pipelines/lion_poses.toml")
    p.add_argument("-o", "--output", default=None, help="output folder (default: the definition's 'output')")
    p.add_argument("--executor", choices=["local", "dask"], default="local",
                   help="'local' process pool (default) or a Dask cluster")
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes (default: the CPU count; 1 runs in this process)")
    p.add_argument("--scheduler", default=None,
                   help="Dask scheduler address (tcp://host:8786); default: a LocalCluster")
    p.add_argument("-v", "--verbose", action="store_true", help="log details and show tracebacks")
    p.add_argument("-q", "--quiet", action="store_true", help="no per-pair progress lines")
    p.set_defaults(func=cmd_run)
    p = sub.add_parser("sdf", help="write the target SDF of MESH to a .npz (dense) or .vdb (OpenVDB) file")
    p.add_argument("mesh", help="the target mesh, or a point cloud (PLY, PCD, XYZ, PTS: the SDF of its "
                                "Poisson surface)")
    p.add_argument("-o", "--output", required=True, help="output file, .npz or .vdb")
    p.add_argument("--resolution", type=int, default=d.grid,
                   help=f"nodes (dense) or voxels (vdb) along the longest side of the padded box "
                        f"(default {d.grid})")
    p.add_argument("--padding", type=float, default=d.padding,
                   help=f"margin on every side, fraction of the mesh's diagonal (default {d.padding})")
    p.add_argument("--half-width", type=float, default=d.vdb_half_width,
                   help=f"vdb band half width in voxels (default {d.vdb_half_width})")
    p.add_argument("--target-sign", choices=list(SIGN_METHODS), default=None,
                   help=f"inside test: winding number or ray parity (default {d.target_sign})")
    p.add_argument("-v", "--verbose", action="store_true", help="log details and show tracebacks")
    p.set_defaults(func=cmd_sdf)
    p = sub.add_parser("render", help="draw result folders or meshes into a PNG (offscreen, matplotlib)")
    p.add_argument("inputs", nargs="+", metavar="RESULT_DIR_OR_MESH",
                   help="result folders of `register` (their registered.*) or mesh files, one panel each")
    p.add_argument("-o", "--output", required=True, help="output PNG")
    p.add_argument("--ground-truth", default=None,
                   help="color by per-vertex error against this mesh (default: a result's own ground truth)")
    p.add_argument("--with-inputs", action="store_true", help="also draw each result's source and target")
    p.add_argument("--up", choices=["x", "y", "z"], default="y", help="up axis of the meshes (default y)")
    p.add_argument("--elev", type=float, default=15.0, help="camera elevation, degrees (default 15)")
    p.add_argument("--azim", type=float, default=-60.0, help="camera azimuth, degrees (default -60)")
    p.add_argument("--max-error", type=float, default=None, help="top of the color scale (default: 99th percentile)")
    p.add_argument("--columns", type=int, default=None, help="panels per row (default: all in one row)")
    p.add_argument("-v", "--verbose", action="store_true", help="log details and show tracebacks")
    p.set_defaults(func=cmd_render)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return args.func(args)
    except MorphModesError as exc:
        if args.verbose:
            raise
        print(f"morphmodes-vol: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("morphmodes-vol: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
