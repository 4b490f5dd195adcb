"""Batch config: ``scans``, ``edit``, ``overrides``, ``output_dir``, ``render``, ``workers``,
``scheduler``, ``memory_per_worker_mb``, ``scan_timeout_s`` -> a validated :class:`Batch`,
one :class:`Job` a scan.

The edit's ``input``/``output`` keys are optional in a batch and ignored: every scan is the
input, and its output is ``output_dir/<stem>_deformed<ext>`` in the scan's format (a double
extension kept: ``x.compressed.ply`` -> ``x_deformed.compressed.ply``). Paths inside the edit (e.g.
``indices: {file: ...}``) are relative to the edit file, or to the batch file for an inline edit.
"""

from __future__ import annotations

import copy
import fnmatch
import hashlib
import json
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, ValidationError

from splatdeform.edit.config import (
    EditConfig,
    ViewCfg,
    input_paths,
    parse_edit,
    read_yaml,
    validation_error,
)
from splatdeform.render.limits import MAX_IMAGE, MIN_IMAGE

from .. import __version__
from ..errors import ConfigError, InputError
from ..io import split_extension
from .sources import Scan, file_kind, find_scans, glob_base, is_glob

PLACEHOLDER_IN = "__batch_input__.ply"
PLACEHOLDER_OUT = "__batch_output__.ply"
THUMBNAIL_PANEL = (800, 600)   # one half of a batch thumbnail, pixels (render.size)
MAX_TIMEOUT_S = 1e7   # seconds (~115 days); larger values overflow the OS wait calls


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class OverrideCfg(_Strict):
    match: str = Field(min_length=1, description="A file-name pattern (fnmatch) of the scans "
                       "this override applies to")
    edit: dict[str, Any] = Field(default={}, description="Edit config keys deep-merged into "
                                 "the edit of the matching scans (in order)")
    render: dict[str, Any] | None = Field(  # BatchRenderCfg keys, merged into the batch's own
        default=None, description="Batch `render` keys over the batch's own for these scans")


class BatchRenderCfg(ViewCfg):
    """As ``deform``'s render (:class:`~splatdeform.edit.config.ViewCfg`, the same keys and
    bounds); the thumbnail is two halves side by side, so the width is at most half the largest
    image, and it is coloured by the file (no ``region``). ``size`` is one half
    (THUMBNAIL_PANEL by default: before and after 800 x 600 each, 1600 x 618 in all).
    ``closeup`` (default true): a second before/after of the same size, ``<stem>.changed.png``,
    framed on the points that moved (the handle and the free region as they visibly move; see
    :func:`splatdeform.render.compare.closeup_camera`), shown under the whole-model one."""

    size: Annotated[list[Annotated[StrictInt, Field(ge=MIN_IMAGE, le=MAX_IMAGE // 2)]],
                    Field(min_length=2, max_length=2)] = Field(
        list(THUMBNAIL_PANEL), description="[w, h] of one half")
    color: Literal["rgb", "elevation", "intensity", "classification"] | None = Field(
        None, description="null: the file's colours, else elevation for LiDAR")
    closeup: bool = Field(True, description="Also <stem>.changed.png, framed on the points "
                          "that moved")


class BatchConfig(_Strict):
    scans: str | list[str] = Field(description="A glob (** allowed), a folder (recursive), a "
                                   ".zip/.tar/.tar.gz archive, or a list of these")
    edit: str | dict[str, Any] = Field(description="An edit file or an inline edit mapping; its "
                                       "input, output and render are filled per scan")
    overrides: list[OverrideCfg] = Field(default=[], description="Per-scan changes to the "
                                         "edit, by file name")
    output_dir: str = Field(min_length=1, description="Where <stem>_deformed<ext>, the "
                            "thumbnails and the reports go (not inside a scanned folder)")
    render: BatchRenderCfg | None = Field(default=None, description="Before/after thumbnails "
                                          "per scan (null: none)")
    workers: StrictInt | None = Field(default=None, ge=1, le=512, description="Local worker "
                                      "processes (null: the number of cores; `--workers` wins)")
    scheduler: str | None = Field(default=None, min_length=1, pattern=r"\S",
                                  description="A Dask scheduler address (tcp://HOST:PORT): run "
                                  "on that cluster instead")
    memory_per_worker_mb: float | None = Field(default=None, gt=0, description="Each worker's "
                                               "memory budget (null: half the RAM / workers "
                                               "running at once)")
    scan_timeout_s: float | None = Field(default=None, gt=0, le=MAX_TIMEOUT_S,
                                         allow_inf_nan=False, description="A scan still "
                                         "running after this is stopped and reported failed")


@dataclass
class Job:
    """One scan's task, picklable (plain data only): what a worker needs."""

    scan: Scan
    edit: dict[str, Any]          # merged edit mapping, without input/output
    base_dir: str                 # where the edit's relative paths start
    output: str                   # output model path
    png: str | None               # thumbnail path
    render: dict[str, Any] | None
    config_hash: str
    memory_budget: float | None = None   # bytes; filled by the runner
    timeout_s: float | None = None       # per-scan limit; filled by the runner

    @property
    def problem(self) -> str | None:
        """Why the scan is reported failed without being processed (None: process it)."""
        return self.scan.problem

    @property
    def sidecar(self) -> str:
        return self.output + ".json"

    @property
    def closeup(self) -> str | None:
        """The close-up thumbnail's path (``<stem>.changed.png`` beside the thumbnail), or None
        without a thumbnail or with ``render.closeup: false``."""
        if not self.png or not self.render or not self.render.get("closeup", True):
            return None
        png = Path(self.png)
        return str(png.with_name(f"{png.stem}.changed.png"))


@dataclass
class Batch:
    source: Path
    output_dir: Path
    jobs: list[Job]
    workers: int | None
    scheduler: str | None
    memory_per_worker_mb: float | None
    scan_timeout_s: float | None = None
    config: dict[str, Any] = field(default_factory=dict)


def deep_merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """A copy of ``base`` with ``extra`` merged in: mappings recursively, anything else replaced."""
    out = copy.deepcopy(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def deformed_name(filename: str) -> str:
    """A scan's output name: ``<stem>_deformed<ext>`` in the scan's own format, its extension
    by :func:`splatdeform.io.split_extension` (``x.compressed.ply`` ->
    ``x_deformed.compressed.ply``)."""
    stem, ext = split_extension(filename)
    return f"{stem}_deformed{ext}"


def _strip_io(edit: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in edit.items() if k not in ("input", "output")}
    if isinstance(out.get("render"), dict):
        out.pop("render")   # the batch's own render: key decides thumbnails
    return out


def validate_edit(edit: dict[str, Any], source: str, prefix: str) -> EditConfig:
    return parse_edit({**edit, "input": PLACEHOLDER_IN, "output": PLACEHOLDER_OUT}, source,
                      prefix)


def _index_files(cfg: EditConfig, base: Path) -> list[tuple[str, Path]]:
    """The files an edit reads besides its input model (indices files)."""
    return [(what, p) for what, p in input_paths(cfg, base) if what != "input model"]


def _hash(data: Any) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:16]


def load_batch(path: str | Path) -> Batch:
    """Read and validate a batch file; ConfigError (exit 2) with one line on any problem."""
    path = Path(path)
    data = read_yaml(path)
    src = str(path)
    try:
        cfg = BatchConfig.model_validate(data)
    except ValidationError as exc:
        raise validation_error(src, exc, roots=(_Strict, EditConfig, ViewCfg)) from None
    base = path.resolve().parent

    # the edit: a file or an inline mapping
    if isinstance(cfg.edit, str):
        edit_path = (base / cfg.edit).resolve()
        edit_src = str(edit_path)
        edit = _strip_io(read_yaml(edit_path))
        edit_base = edit_path.parent
        prefix = ""
    else:
        edit_src, edit, edit_base, prefix = src, _strip_io(cfg.edit), base, "edit"
    reads: list[tuple[str, Path]] = [("batch file", path)]
    if isinstance(cfg.edit, str):
        reads.append(("edit file", edit_path))
    reads += _index_files(validate_edit(edit, edit_src, prefix), edit_base)
    for i, ov in enumerate(cfg.overrides):
        merged = deep_merge(edit, _strip_io(ov.edit))
        reads += _index_files(validate_edit(merged, src, f"overrides[{i}].edit"), edit_base)

    output_dir = (base / cfg.output_dir).resolve()
    patterns = [cfg.scans] if isinstance(cfg.scans, str) else list(cfg.scans)
    if not patterns:
        raise ConfigError(f"{src}: scans: expected a glob, a folder, an archive or a list of them")
    scans = find_scans(patterns, base, exclude=output_dir, source=src)
    _check_output_dir(patterns, base, output_dir, scans, src)

    render = _render_options(cfg.render.model_dump() if cfg.render else None, base, reads,
                             "render", src)
    override_renders = [
        None if ov.render is None else _render_options(
            {**(cfg.render.model_dump(exclude_unset=True) if cfg.render else {}), **ov.render},
            base, reads, f"overrides[{i}].render", src)
        for i, ov in enumerate(cfg.overrides)]
    jobs: list[Job] = []
    by_output: dict[str, Scan] = {}
    for scan in scans:
        if scan.problem is not None:   # reported failed, never opened: no outputs
            jobs.append(Job(scan, edit, str(edit_base), "", None, None,
                            _hash({"problem": scan.name})))
            continue
        merged, scan_render = edit, render
        for ov, ov_render in zip(cfg.overrides, override_renders, strict=True):
            if fnmatch.fnmatch(scan.filename, ov.match) or fnmatch.fnmatch(scan.name, ov.match):
                merged = deep_merge(merged, _strip_io(ov.edit))
                scan_render = ov_render if ov_render is not None else scan_render
        out = output_dir / deformed_name(scan.filename)
        if str(out) in by_output:
            raise ConfigError(f"{src}: scans: {scan.name} and {by_output[str(out)].name} would "
                              f"both write {out.name}; rename one")
        by_output[str(out)] = scan
        png = str(output_dir / f"{scan.stem}.png") if scan_render else None
        digest = _hash({"edit": merged, "render": scan_render, "source": scan.identity,
                        "version": __version__})
        jobs.append(Job(scan, merged, str(edit_base), str(out), png, scan_render, digest))
    _check_paths(src, output_dir, reads + [("scan", Path(s.path)) for s in scans], jobs)
    return Batch(path, output_dir, jobs, cfg.workers, cfg.scheduler, cfg.memory_per_worker_mb,
                 cfg.scan_timeout_s, cfg.model_dump())


def _render_options(render: dict[str, Any] | None, base: Path, reads: list, key: str,
                   src: str) -> dict[str, Any] | None:
    """Validated render options (an override's: the batch's keys with its own on top) with
    the camera file resolved against the batch file and read up front (a bad one fails the
    batch, named)."""
    if render is None:
        return None
    try:
        render = BatchRenderCfg.model_validate(render).model_dump()
    except ValidationError as exc:
        raise validation_error(src, exc, prefix=key, roots=(_Strict, ViewCfg)) from None
    if render.get("camera"):   # relative to the batch file; read, never written
        render["camera"] = str((base / render["camera"]).resolve())
        reads.append((f"{key}.camera", Path(render["camera"])))
        from ..render.camera import load_camera

        load_camera(render["camera"])
    return render


REPORT_FILES = ("report.json", "report.csv", "index.html")


def _identity(p: Path) -> tuple:
    """What makes two paths the same file: (device, inode) when it exists, else the path."""
    try:
        st = p.stat()
        return (st.st_dev, st.st_ino)
    except OSError:
        return (str(p.resolve()),)


def _check_paths(src: str, output_dir: Path, inputs: list[tuple[str, Path]],
                 jobs: list[Job]) -> None:
    """Before any work: no output of the batch is one of its inputs (batch file, edit file,
    indices files, scans: same file, not same spelling) or another output, and none exists as
    something other than a regular file (a FIFO, a device, a folder). Linear in the number of
    scans (one stat per path)."""
    if output_dir.exists() and not output_dir.is_dir():
        raise InputError(f"{src}: output_dir: {output_dir} exists and is not a folder")
    seen: dict[tuple, str] = {}
    for what, p in inputs:
        seen.setdefault(_identity(p), f"{what} {p}")
    outputs = [(f"output_dir: {name}", output_dir / name) for name in REPORT_FILES]
    for job in jobs:
        if job.problem is None:
            outputs += [(f"{job.scan.name}: output", Path(job.output)),
                        (f"{job.scan.name}: sidecar", Path(job.sidecar))]
            if job.png:
                from ..render.camera import camera_sidecar  # where its camera file goes

                outputs += [(f"{job.scan.name}: thumbnail", Path(job.png)),
                            (f"{job.scan.name}: thumbnail camera", camera_sidecar(job.png))]
            if job.closeup:
                outputs += [(f"{job.scan.name}: close-up thumbnail", Path(job.closeup)),
                            (f"{job.scan.name}: close-up camera", camera_sidecar(job.closeup))]
    for what, out in outputs:
        try:
            mode = out.stat().st_mode
        except OSError:
            mode = None
        if mode is not None and not stat.S_ISREG(mode):
            raise InputError(f"{src}: {what} {out} exists and is {file_kind(mode)}; expected a "
                             "regular file to replace (or nothing)")
        key = _identity(out)
        if key in seen:
            raise InputError(f"{src}: {what} {out} is the {seen[key]}; refusing to overwrite "
                             "it, choose another output_dir")
        seen[key] = f"{what} {out}"


def _inside(child: Path, parent: Path) -> bool:
    try:
        child.relative_to(parent)
        return True
    except ValueError:
        return False


SYSTEM_DIRS = (Path("/dev"), Path("/proc"), Path("/sys"))


def _check_output_dir(patterns: list[str], base: Path, output_dir: Path, scans: list[Scan],
                      src: str) -> None:
    """Refuse an output_dir that a rerun would scan again (outputs becoming inputs): inside or
    equal to a scanned folder or a glob's folder; and one under /dev, /proc or /sys."""
    for system in SYSTEM_DIRS:
        if _inside(output_dir, system):
            raise ConfigError(f"{src}: output_dir: {output_dir} is under {system} (devices and "
                              "kernel files); choose an ordinary folder")
    for pattern in patterns:   # a glob's folder is a scan folder, whatever it matches now
        folder = glob_base(str(base / pattern)) if is_glob(pattern) else None
        if folder is not None and _inside(output_dir, folder):
            raise ConfigError(f"{src}: output_dir: {output_dir} is inside the scan folder "
                              f"{folder} of {pattern!r}; choose a folder outside the inputs")
    for pattern in patterns:
        if is_glob(pattern):
            pat = str(base / pattern)
            probes = [str(output_dir / deformed_name(s.filename)) for s in scans[:50]]
            recursive = "**" in pattern and _inside(output_dir, glob_base(pat))
            if recursive or any(fnmatch.fnmatch(p, pat) for p in probes):
                raise ConfigError(f"{src}: output_dir: {output_dir} would be matched by scans "
                                  f"pattern {pattern!r}; choose a folder outside the inputs")
        else:
            p = (base / pattern).resolve()
            if p.is_dir() and _inside(output_dir, p):
                raise ConfigError(f"{src}: output_dir: {output_dir} is inside the scanned input "
                                  f"folder {p}; choose a folder outside it")
