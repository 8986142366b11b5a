"""Pipeline definitions: a TOML file naming the pairs, the options and the outputs.

Format reference: docs/pipelines.md. Every error names the file and the key.
"""

from __future__ import annotations

import csv
import dataclasses
import glob as globmod
import itertools
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import OptionError, PipelineError
from ..export import MESH_FORMATS
from ..options import PRESETS, RegistrationOptions, read_toml

__all__ = ["Pipeline", "PairSpec", "load_pipeline", "parse_pipeline"]

_TOP_KEYS = {"name", "data_dir", "output", "cache", "pairs", "options", "sweep", "outputs"}
_PAIR_KEYS = {"source", "targets", "list", "all", "manifest", "ground_truth"}
_OUTPUT_KEYS = {"format", "plot"}
_GROUND_TRUTH = ("target", "none")


@dataclass(frozen=True)
class PairSpec:
    """One registration of a pipeline: what to register, how, and where to write it.

    Attributes
    ----------
    name : str
        Unique within the pipeline; the name of the pair's output folder.
    source, target : Path
    ground_truth : Path or None
        Mesh whose vertex ``i`` is where source vertex ``i`` belongs.
    options : RegistrationOptions
    variant : dict
        The swept option values of this pair (empty without a ``[sweep]``).
    outdir : Path
    mesh_format : str
        Format of ``registered.*``; ``"source"`` keeps the source's.
    cache_dir : Path
    landmarks : Path or None
        Landmark CSV of the pair (:mod:`morphmodes_vol.landmarks`).
    """

    name: str
    source: Path
    target: Path
    ground_truth: Path | None
    options: RegistrationOptions
    variant: dict = field(default_factory=dict)
    outdir: Path = Path(".")
    mesh_format: str = "source"
    cache_dir: Path = Path(".")
    landmarks: Path | None = None

    @property
    def resolved_format(self) -> str:
        if self.mesh_format != "source":
            return self.mesh_format
        ext = self.source.suffix.lower().lstrip(".")
        return ext if ext in MESH_FORMATS else "ply"


@dataclass(frozen=True)
class Pipeline:
    """A parsed pipeline definition.

    Attributes
    ----------
    name : str
    path : Path
        The TOML file.
    output : Path
        Root output folder: ``pairs/<name>/`` per pair, ``summary.*``, and by default ``cache/``.
    cache_dir : Path
    pairs : list of PairSpec
    plot_metric : str
        Metric drawn per pair in ``summary.png``.
    """

    name: str
    path: Path
    output: Path
    cache_dir: Path
    pairs: list[PairSpec]
    plot_metric: str = "ground_truth_error"


def load_pipeline(path: str | os.PathLike, output: str | os.PathLike | None = None) -> Pipeline:
    """Read and check a pipeline definition.

    Parameters
    ----------
    path : path of the TOML file
    output : path, optional
        Overrides the file's ``output`` (relative to the current directory).

    Raises
    ------
    PipelineError
        Naming the file and the key, for any invalid entry.
    """
    path = Path(path)
    return parse_pipeline(read_toml(path, PipelineError, "pipeline file"), path, output)


class _Checker:
    """Error messages that name the file and the key."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, key: str, what: str):
        raise PipelineError(f"{self.path}: {key or 'top level'}: {what}")

    def keys(self, table: Any, allowed: set[str], where: str) -> dict:
        if not isinstance(table, dict):
            self.fail(where, "must be a table")
        unknown = sorted(set(table) - allowed)
        if unknown:
            prefix = f"{where}." if where else ""
            self.fail(f"{prefix}{unknown[0]}", f"unknown key; expected one of {sorted(allowed)}")
        return table

    def string(self, table: dict, key: str, where: str, default: str | None = None) -> str | None:
        value = table.get(key, default)
        if value is not None and not isinstance(value, str):
            self.fail(f"{where}{key}", f"must be a string, got {value!r}")
        return value


def _expand(value: str, ck: _Checker, key: str) -> str:
    expanded = os.path.expanduser(os.path.expandvars(value))
    left = re.search(r"\$\{?\w+\}?", expanded)
    if left:
        ck.fail(key, f"environment variable {left.group(0)} is not set")
    return expanded


def _data_dir(doc: dict, base: Path, ck: _Checker) -> Path:
    value = ck.string(doc, "data_dir", "")
    if value is None:
        return base
    if value == "@shared":
        from ..datasets import shared_data_dir

        found = shared_data_dir()
        if found is None:
            ck.fail("data_dir", "'@shared': the shared data folder is absent (set MORPHMODES_DATA)")
        return found
    path = _norm(base / _expand(value, ck, "data_dir"))
    if not path.is_dir():
        ck.fail("data_dir", f"{path} is not a folder")
    return path


def _options(doc: dict, ck: _Checker) -> RegistrationOptions:
    table = doc.get("options", {})
    names = {f.name for f in dataclasses.fields(RegistrationOptions)}
    ck.keys(table, names | {"preset"}, "options")
    try:  # the path of the command line's --preset, --config and --set too
        return RegistrationOptions.from_table(table)
    except (OptionError, TypeError) as exc:
        ck.fail("options.preset" if table.get("preset", "default") not in PRESETS else "options", str(exc))


def _variants(doc: dict, base: RegistrationOptions, ck: _Checker) -> list[tuple[dict, RegistrationOptions]]:
    table = doc.get("sweep", {})
    names = {f.name for f in dataclasses.fields(RegistrationOptions)}
    ck.keys(table, names, "sweep")
    for key, values in table.items():
        if not isinstance(values, list) or not values:
            ck.fail(f"sweep.{key}", f"must be a non-empty list of values, got {values!r}")
    out = []
    for combo in itertools.product(*table.values()):
        variant = dict(zip(table, combo))
        try:
            out.append((variant, base.replace(**variant)))
        except (OptionError, TypeError) as exc:
            ck.fail("sweep", str(exc))
    return out


def _glob(pattern: str, data: Path, ck: _Checker, key: str) -> list[Path]:
    full = str(data / _expand(pattern, ck, key))
    found = sorted(Path(p) for p in globmod.glob(full) if Path(p).is_file())
    if not found:
        ck.fail(key, f"{full!r} matches no file")
    return found


def _raw_pairs(table: dict, data: Path, ck: _Checker) -> list[tuple[Path, Path, Path | None | str, str | None,
                                                                     Path | None]]:
    """(source, target, ground truth, name, landmarks) before variants; ground truth may be
    'target'; landmarks come from list entries and manifest rows only."""
    modes = [k for k in ("targets", "list", "all", "manifest") if k in table]
    if len(modes) != 1:
        ck.fail("pairs", "needs exactly one of 'targets' (with 'source'), 'list', 'all', 'manifest'; "
                         f"found {modes or 'none'}")
    mode = modes[0]
    if ("source" in table) != (mode == "targets"):
        ck.fail("pairs.source", "goes with 'targets' (a glob of targets against one source), and only with it")
    gt = ck.string(table, "ground_truth", "pairs.", "none")

    def resolve(value, key: str, base: Path) -> Path:
        if not isinstance(value, str) or not value:
            ck.fail(key, f"must be a path string, got {value!r}")
        return _norm(base / _expand(value, ck, key))

    if gt not in _GROUND_TRUTH:
        ck.fail("pairs.ground_truth", f"must be one of {_GROUND_TRUTH} (list entries and manifest "
                                      f"rows may name a mesh), got {gt!r}")
    default_gt = "target" if gt == "target" else None
    if mode == "targets":
        source = resolve(table["source"], "pairs.source", data)
        targets = _glob(ck.string(table, "targets", "pairs."), data, ck, "pairs.targets")
        return [(source, t, default_gt, None, None) for t in targets if t.resolve() != source.resolve()]
    if mode == "all":
        files = _glob(ck.string(table, "all", "pairs."), data, ck, "pairs.all")
        if len(files) < 2:
            ck.fail("pairs.all", "matches fewer than two files")
        return [(a, b, default_gt, None, None) for a, b in itertools.permutations(files, 2)]
    if mode == "list":
        items = table["list"]
        if not isinstance(items, list) or not items:
            ck.fail("pairs.list", "must be a non-empty list of {source, target[, ground_truth, name, "
                                  "landmarks]} tables")
        rows = []
        for i, item in enumerate(items):
            where = f"pairs.list[{i}]"
            if isinstance(item, list) and len(item) == 2:
                item = {"source": item[0], "target": item[1]}
            ck.keys(item, {"source", "target", "ground_truth", "name", "landmarks"}, where)
            for k in ("source", "target"):
                if k not in item:
                    ck.fail(f"{where}.{k}", "is missing")
            rows.append(_row(item, data, default_gt, resolve, ck, where))
        return rows
    manifest = resolve(table["manifest"], "pairs.manifest", data)
    try:
        with open(manifest, newline="") as fh:
            reader = csv.DictReader(fh)
            if not reader.fieldnames or not {"source", "target"} <= set(reader.fieldnames):
                ck.fail("pairs.manifest", f"{manifest} needs a header with columns 'source' and 'target'")
            extra = sorted(set(reader.fieldnames) - {"source", "target", "ground_truth", "name", "landmarks"})
            if extra:
                ck.fail("pairs.manifest", f"{manifest}: unknown column {extra[0]!r}")
            rows = [_row({k: v for k, v in r.items() if v}, manifest.parent, default_gt, resolve, ck,
                         f"pairs.manifest line {n + 2}") for n, r in enumerate(reader)]
    except OSError as exc:
        ck.fail("pairs.manifest", f"cannot read {manifest} ({exc.strerror})")
    if not rows:
        ck.fail("pairs.manifest", f"{manifest} lists no pair")
    return rows


def _row(item: dict, base: Path, default_gt, resolve, ck: _Checker, where: str):
    source = resolve(item["source"], f"{where}.source", base)
    target = resolve(item["target"], f"{where}.target", base)
    gt = item.get("ground_truth")
    if gt is None:
        gt = default_gt
    elif gt == "target":
        gt = "target"
    elif gt != "none":
        gt = resolve(gt, f"{where}.ground_truth", base)
    else:
        gt = None
    name = item.get("name")
    if name is not None and (not isinstance(name, str) or not re.fullmatch(r"[\w.=+-]+", name)):
        ck.fail(f"{where}.name", f"must be letters, digits and . _ = + - only, got {name!r}")
    landmarks = item.get("landmarks")
    if landmarks is not None:
        landmarks = resolve(landmarks, f"{where}.landmarks", base)
    return source, target, gt, name, landmarks


def _norm(path: Path) -> Path:
    return Path(os.path.normpath(path))


def _variant_label(variant: dict) -> str:
    return "__".join(f"{k}={v}" for k, v in variant.items())


def parse_pipeline(doc: dict, path: str | os.PathLike, output: str | os.PathLike | None = None) -> Pipeline:
    """Check an already-read TOML document (see :func:`load_pipeline`).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> p = parse_pipeline({"pairs": {"list": [["a.obj", "b.obj"], ["b.obj", "a.obj"]]},
    ...                     "sweep": {"grid": [16, 24]}}, folder / "study.toml")
    >>> [pair.name for pair in p.pairs]
    ['a__b__grid=16', 'a__b__grid=24', 'b__a__grid=16', 'b__a__grid=24']
    """
    path = Path(path)
    ck = _Checker(path)
    ck.keys(doc, _TOP_KEYS, "")
    base = path.resolve().parent
    name = ck.string(doc, "name", "", path.stem)
    data = _data_dir(doc, base, ck)
    if output is not None:
        out = Path(output)
    else:
        out = _norm(base / _expand(ck.string(doc, "output", "", f"../out/{name}"), ck, "output"))
    cache = ck.string(doc, "cache", "")
    cache_dir = _norm(base / _expand(cache, ck, "cache")) if cache else out / "cache"
    outputs = ck.keys(doc.get("outputs", {}), _OUTPUT_KEYS, "outputs")
    fmt = ck.string(outputs, "format", "outputs.", "source")
    if fmt not in MESH_FORMATS + ("source",):
        ck.fail("outputs.format", f"must be one of {MESH_FORMATS + ('source',)}, got {fmt!r}")
    plot = ck.string(outputs, "plot", "outputs.", "ground_truth_error")

    base_options = _options(doc, ck)
    variants = _variants(doc, base_options, ck)
    if "pairs" not in doc:
        ck.fail("pairs", "is missing: which meshes to register")
    table = ck.keys(doc["pairs"], _PAIR_KEYS, "pairs")
    specs: list[PairSpec] = []
    seen: dict[str, int] = {}
    for source, target, gt, pair_name, landmarks in _raw_pairs(table, data, ck):
        stem = pair_name or f"{source.stem}__{target.stem}"
        for variant, options in variants:
            label = stem + (f"__{_variant_label(variant)}" if variant else "")
            count = seen.get(label, 0)
            seen[label] = count + 1
            unique = label if count == 0 else f"{label}__{count + 1}"
            specs.append(PairSpec(
                name=unique, source=source, target=target,
                ground_truth=target if gt == "target" else gt,
                options=options, variant=variant, outdir=out / "pairs" / unique,
                mesh_format=fmt, cache_dir=cache_dir, landmarks=landmarks,
            ))
    return Pipeline(name=name, path=path, output=out, cache_dir=cache_dir, pairs=specs, plot_metric=plot)
