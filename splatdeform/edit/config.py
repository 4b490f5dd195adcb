"""YAML edit configs -> validated config objects.

Every error is one :class:`ConfigError` line naming the file and the key path, e.g.
``edit.yaml: regions.fixed[0].box.min: expected a list of 3 numbers``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    Field,
    StrictInt,
    ValidationError,
    field_validator,
    model_validator,
)

from splatdeform.basis.names import BACKENDS
from splatdeform.deform.gaussians import DEFAULT_COVARIANCE
from splatdeform.deform.split import DEFAULT_SPLIT
from splatdeform.edit.points_cfg import PairsFileCfg, PointsCfg
from splatdeform.edit.schema import (
    MAX_VALUE,
    Number,
    Strict,
    Vec3,
    shown,
)
from splatdeform.edit.selectors import SelectorCfg
from splatdeform.edit.yaml_read import read_yaml
from splatdeform.errors import ConfigError
from splatdeform.model import MAX_SCALE, MIN_SCALE
from splatdeform.rbf.defaults import (
    DEFAULT_MAX_CENTERS,
    DEFAULT_METHOD,
    DEFAULT_THINNING,
    DEFAULT_TOLERANCE,
)
from splatdeform.render import limits as lim  # the view bounds, one definition

MAX_CONTROL_POINTS = 128  # curve control points (the renderer's storage-buffer limit)
_Strict = Strict  # the root of the edit config's models (key paths come from their fields)


class RegionsCfg(_Strict):
    units: Literal["model", "relative"] = Field("model", description="`relative`: in [0, 1]^3 "
                                                "of the bounding box (radii: of its diagonal)")
    fixed: list[SelectorCfg] = Field(default_factory=list, description="Points that stay bit "
                                     "for bit; required but for a `points:` edit alone")
    handle: list[SelectorCfg] | None = Field(None, description="Points a `handle:` moves by "
                                             "its 4x4 map (required with `handle:`)")

    @field_validator("fixed")
    @classmethod
    def _given_not_empty(cls, v: list) -> list:   # only when given: absent is points: alone
        if not v:
            raise ValueError("an empty list selects no point; give at least one selector, or "
                             "leave the key out (a points: edit alone)")
        return v


MAX_DEGREES = 1e6  # a rotation angle beyond this is a typo or an attack, not an edit
# a handle scale outside MIN_SCALE..MAX_SCALE (by magnitude) is degenerate (the one bound,
# splatdeform.model's: convert --scale holds to it too)
MIN_SINGULAR_RATIO = 1e-9  # a handle's 3x3 part: smallest singular value / largest, at least


class RotateCfg(_Strict):
    axis: Vec3 = Field(default=[0.0, 0.0, 1.0], description="The rotation axis, a non-zero "
                       "direction in model coordinates (never scaled by relative units)")
    degrees: Number = Field(default=0.0, description="The angle about `axis` through the pivot "
                            "(right-handed), within +-1e6")

    @field_validator("axis")
    @classmethod
    def _axis(cls, axis: list[float]) -> list[float]:
        norm = math.hypot(*axis)
        if not (1e-12 < norm <= MAX_VALUE):
            raise ValueError(f"expected a non-zero rotation axis with components within "
                             f"+-{MAX_VALUE:g}, got {axis}")
        return axis

    @field_validator("degrees")
    @classmethod
    def _degrees(cls, degrees: float) -> float:
        if abs(degrees) > MAX_DEGREES:
            raise ValueError(f"expected an angle within +-{MAX_DEGREES:g} degrees, got "
                             f"{degrees}")
        return degrees


def _bounded(values: list[float], what: str) -> list[float]:
    if any(abs(v) > MAX_VALUE for v in values):
        raise ValueError(f"expected {what} within +-{MAX_VALUE:g}, got {values}")
    return values


class TransformCfg(_Strict):
    pivot: Literal["centroid"] | Vec3 = Field("centroid", description="What the scale and "
                                              "rotation are about (`centroid`: the handle's)")
    scale: Number | Vec3 = Field(default=1.0, description="A factor, or one per axis [sx, sy, "
                                 "sz], applied first (magnitudes between 1e-6 and 1e6)")
    rotate: RotateCfg = Field(default=RotateCfg(), description="Applied after the scale")
    translate: Vec3 = Field(default=[0.0, 0.0, 0.0], description="Applied last (in relative "
                            "units scaled by the bounding-box extent per axis)")

    @field_validator("scale")
    @classmethod
    def _scale(cls, scale: float | list[float]) -> float | list[float]:
        for s in scale if isinstance(scale, list) else [scale]:
            if not MIN_SCALE <= abs(s) <= MAX_SCALE:
                raise ValueError(f"expected scale factors between {MIN_SCALE:g} and "
                                 f"{MAX_SCALE:g} in magnitude (a vanishing or huge scale is "
                                 f"degenerate), got {scale}")
        if isinstance(scale, list):  # the 3x3 part's singular values are the |factors|
            problem = _singular_problem(np.abs(np.asarray(scale, dtype=np.float64)))
            if problem is not None:
                raise ValueError(problem)
        return scale

    @field_validator("translate")
    @classmethod
    def _translate(cls, v: list[float]) -> list[float]:
        return _bounded(v, "a translation")

    @field_validator("pivot")
    @classmethod
    def _pivot(cls, v):
        return v if isinstance(v, str) else _bounded(v, "a pivot")


def _singular_problem(sv: np.ndarray) -> str | None:
    """Why a linear map with singular values ``sv`` cannot be a handle transform (None: it
    can): it collapses the handle (smallest below MIN_SCALE, or below MIN_SINGULAR_RATIO of the
    largest)."""
    small, large = float(sv.min()), float(sv.max())
    if small >= MIN_SCALE and small >= MIN_SINGULAR_RATIO * large:
        return None
    return (f"singular or nearly singular (singular values of the 3x3 part {large:.3g} .. "
            f"{small:.3g}; expected the smallest at least {MIN_SCALE:g} and at least "
            f"{MIN_SINGULAR_RATIO:g} of the largest): it would collapse the handle")


def handle_matrix_problem(matrix: Any, bound: float | None = MAX_VALUE) -> str | None:
    """Why ``matrix`` (a 4x4 affine transform, or its top 3x4 or 3x3 part) cannot be a
    handle's transform; None when it can. ``bound``: the largest entry magnitude (None: any
    finite entry, e.g. a transform composed about a far pivot)."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return "expected 4 rows of 4 numbers"
    if m.shape not in ((4, 4), (3, 4), (3, 3)):
        return f"expected 4 rows of 4 numbers, got shape {m.shape}"
    if not np.isfinite(m).all():
        return "expected finite entries"
    if bound is not None and np.abs(m).max() > bound:
        return f"expected entries within +-{bound:g}"
    if m.shape == (4, 4) and not np.allclose(m[3], [0, 0, 0, 1]):
        return "the last row must be [0, 0, 0, 1] (affine)"
    return _singular_problem(np.linalg.svd(m[:3, :3], compute_uv=False))


def check_handle_matrix(matrix: Any, key: str, *, bound: float | None = MAX_VALUE) -> None:
    """Refuse a handle transform that is not a usable affine map: ConfigError naming ``key``
    (e.g. ``handles[1].matrix``) when ``matrix`` (4x4, or its 3x4 / 3x3 part) has non-finite
    or out-of-bound entries, a last row other than [0, 0, 0, 1], or a 3x3 part whose smallest
    singular value is below MIN_SCALE or below MIN_SINGULAR_RATIO of its largest (every handle
    point would collapse towards a plane, a line or a point). ``bound``: the largest entry
    magnitude (:data:`MAX_VALUE`, as in a config; None: any finite entry)."""
    problem = handle_matrix_problem(matrix, bound)
    if problem is not None:
        raise ConfigError.at(key, problem)


class HandleCfg(_Strict):
    transform: TransformCfg | None = Field(None, description="Scale, rotate, translate about "
                                           "a pivot (one of `transform`, `matrix`)")
    matrix: Annotated[list[Annotated[list[Number], Field(min_length=4, max_length=4)]],
                      Field(min_length=4, max_length=4)] | None = Field(
        None, description="4x4 affine rows, the last [0, 0, 0, 1]; not singular")

    @field_validator("matrix")
    @classmethod
    def _matrix(cls, matrix: list[list[float]] | None) -> list[list[float]] | None:
        problem = None if matrix is None else handle_matrix_problem(matrix)
        if problem is not None:
            raise ValueError(problem)
        return matrix

    @model_validator(mode="after")
    def _one(self) -> HandleCfg:
        if (self.transform is None) == (self.matrix is None):
            raise ValueError("expected exactly one of transform, matrix")
        return self


class HandleEntryCfg(HandleCfg):
    """One entry of ``handles:``: the ``handle:`` form plus its own ``region`` (selectors)."""

    region: list[SelectorCfg] = Field(min_length=1, description="This handle's points (not "
                                      "overlapping the fixed region or another handle)")


class CurveCfg(_Strict):
    control_points: list[Vec3] = Field(min_length=2, max_length=MAX_CONTROL_POINTS,
                                       description="The B-spline's control points (at least "
                                       "degree + 1), each snapped to the nearest model point")
    moved_to: list[Vec3] = Field(description="Where each control point goes (same count): "
                                 "delta_c = moved_to - control_points")
    degree: int = Field(default=3, ge=1, le=5, description="The spline degree")
    capture_radius: Number = Field(gt=0, description="Model points within this distance of "
                                   "the curve form the curve band that moves")
    parametrization: Literal["uniform", "chord"] = Field("chord", description="Knot spacing")


class BoundaryCfg(_Strict):
    continuity: Literal[0, 1, 2] = Field(default=2, description="C0 / C1 / C2 at the region "
                                         "borders: 1 / 2 / 3 rings of constraints")
    neighbors: int = Field(default=10, ge=3, le=200, description="The kNN size that makes the "
                           "rings of a point cloud (meshes use their faces)")


class FitCfg(_Strict):
    """``fit:`` (a kept ring point misses its target by at most k * tolerance * the largest
    control-point move). Defaults from the measured fit table on the Benchmarks page
    (docs/benchmarks.md)."""

    tolerance: float = Field(DEFAULT_TOLERANCE, gt=0, lt=1, description="Largest constraint "
                             "error |r_ic| over the kept constraints, in M's coordinates")
    max_centers: int = Field(DEFAULT_MAX_CENTERS, ge=0, le=20000, description="Where the "
                             "incremental fit stops (see `on_not_converged`)")
    method: Literal["auto", "incremental", "exact"] = Field(DEFAULT_METHOD, description="`auto`:"
                                                            " the cheapest by predicted cost")
    selection: Literal["greedy", "fps"] = Field("greedy", description="How the incremental fit "
                                                "picks centers (`fps`: farthest point)")
    thinning: float = Field(DEFAULT_THINNING, ge=0, le=20, description="Ring thinning cell, in "
                            "ring widths (0 keeps every ring point)")
    threads: int | None = Field(None, ge=1, le=1024, description="The dense solve's threads "
                                "(null: the CPUs this process may use)")
    on_not_converged: Literal["warn", "error"] = Field("warn", description="`error`: a fit "
                                                       "above the tolerance exits 1, no output")


class SaveCfg(_Strict):
    """``save:``: options of the writers that quantise or encode (``io.options.writing``)."""

    spz_version: Literal[3, 4] | None = Field(  # .spz: 4 by default, 3 for older readers
        default=None, description=".spz version written (null: 4; 3 for older readers)")
    sog_quality: Literal["reference", "fast"] | None = Field(  # SOG SH encoder (reference)
        default=None, description="The SOG writer's SH encoder (null: `reference`)")
    sog_order: Literal["morton", "keep"] | None = Field(  # SOG splat order (morton)
        default=None, description="The SOG writer's splat order (null: `morton`, Z-order by "
        "position as splat-transform writes it; `keep`: the input's)")
    pcd_data: Literal["ascii", "binary", "binary_compressed"] | None = Field(  # input's own
        default=None, description="The PCD `DATA` encoding written (null: the input's own)")


class GaussiansCfg(_Strict):
    """``gaussians:``: how 3D Gaussian splats' covariances deform (the Splats guide,
    docs/guides/splats.md: "Covariance modes")."""

    covariance: Literal["jacobian", "rotation", "limited"] = Field(
        DEFAULT_COVARIANCE, description="`jacobian`: J Sigma J^T; `rotation`: turned, shape kept; "
        "`limited`: J Sigma J^T, axis ratio growing at most 2x")
    split: Literal["auto", "off"] = Field(
        DEFAULT_SPLIT, description="`auto`: split free-region splats one Gaussian cannot "
        "follow into children (the written file, streamed or not, and `deform --render`; the "
        "editor's live pose and animation frames draw them unsplit); it also governs surfel "
        "discs with tangent axes (`ux`..`vz`), split by the same rule (round surfels are never "
        "split); `off`: keep the point count")


UpAxis = Literal["+x", "+y", "+z", "-x", "-y", "-z"]
ViewColor = Literal["rgb", "elevation", "intensity", "classification", "region"]
Angle = Annotated[float, Field(ge=-lim.MAX_ANGLE, le=lim.MAX_ANGLE)]


class ViewCfg(_Strict):
    """The view keys ``deform``'s ``render`` and a batch's ``render`` share (one definition:
    the batch's thumbnail narrows ``size`` and ``color``, and adds ``closeup``)."""

    size: Annotated[list[Annotated[StrictInt, Field(ge=lim.MIN_IMAGE, le=lim.MAX_IMAGE)]],
                    Field(min_length=2, max_length=2)] = Field(list(lim.DEFAULT_SIZE),
                                                               description="[w, h]")
    azimuth: Angle = Field(30.0, description="Degrees about the up axis")
    elevation: Angle | None = Field(None, description="Degrees above the horizon (null: 20, or "
                                    "40 for flat scenes: LiDAR, terrain)")
    fov: float = Field(lim.DEFAULT_FOV, ge=lim.MIN_FOV, le=lim.MAX_FOV,
                       description="The lens angle, degrees")
    zoom: float = Field(1.0, ge=lim.MIN_ZOOM, le=lim.MAX_ZOOM,
                        description="Narrows the view about the target")
    up: UpAxis | None = Field(None, description="The axis shown up (null: the file's convention)")
    roll: float = Field(0.0, ge=-lim.MAX_ROLL, le=lim.MAX_ROLL,
                        description="Degrees about the view direction")
    camera: str | None = Field(None, description="A camera file (OUT.camera.json), relative to "
                               "the config file")
    color: ViewColor | None = Field(
        None, description="null: the file's colours, else elevation for LiDAR")


class RenderCfg(ViewCfg):
    output: str | None = Field(None, description="A .png (frames >= 2: .gif or a folder); null: "
                               "only `select -o` / `deform --render` name the image")
    frames: int = Field(0, ge=0, le=lim.MAX_FRAMES, description=">= 2: the edit animated")

    @model_validator(mode="after")
    def _output_kind(self) -> RenderCfg:
        if self.output is not None:
            check_render_output(self.output, self.frames)
        return self


def check_render_output(output: str, frames: int) -> None:
    """ValueError unless ``output`` suits the image kind: .png for one image; with frames >= 2 a
    .gif (a .png name becomes .gif) or a suffix-less folder of PNGs."""
    suffix = Path(output).suffix.lower()
    allowed = (".png",) if frames < 2 else (".gif", ".png", "")
    if suffix not in allowed:
        what = "a .png file" if frames < 2 else "a .gif file or a folder (no suffix)"
        raise ValueError(f"output: expected {what}, got {output!r}")


class EditConfig(_Strict):
    input: str = Field(description="The model to edit, relative to the config file")
    output: str = Field(description="The deformed model (never the input; format by extension)")
    regions: RegionsCfg = Field(RegionsCfg(), description="Fixed and handle regions, units")
    handle: HandleCfg | None = Field(None, description="One handle (points: `regions.handle`)")
    handles: list[HandleEntryCfg] | None = Field(None, min_length=1, max_length=32,
                                                 description="Several handles, each with a region")
    curve: CurveCfg | None = Field(None, description="A curve edit (B-spline control points)")
    points: PointsCfg | None = Field(None, description="Control-point pairs (rubber sheet)")
    boundary: BoundaryCfg = Field(BoundaryCfg(), description="Region border continuity, kNN")
    fit: FitCfg = Field(FitCfg(), description="The RBF fit")
    normals: Literal["keep", "estimate"] = Field("keep", description="`estimate`: Open3D normals")
    backend: Literal[BACKENDS] = Field("auto", description="Basis backend (`auto`: OpenCL when "
                                       "a device exists, else numpy)")
    device: str | None = Field(None, description="OpenCL device: \"P:D\" or a name substring")
    render: RenderCfg | None = Field(None, description="The before/after image and its camera")
    gaussians: GaussiansCfg = Field(GaussiansCfg(), description="How 3D Gaussian splats deform")
    save: SaveCfg = Field(SaveCfg(), description="Options of the quantising/encoding writers")
    memory_budget: str | int | None = Field(None, description="e.g. 2GB: `deform` streams above "
                                            "it (null: half the RAM)")

    @model_validator(mode="after")
    def _metaphor(self) -> EditConfig:
        if self.handles is not None and (self.handle is not None or self.regions.handle):
            raise ValueError("handles: not together with handle or regions.handle; put every "
                             "handle (with its region) under handles")
        if self.handle is not None and self.curve is not None:
            raise ValueError("expected one of handle, curve (use handles: to combine handles "
                             "with a curve)")
        if self.handle is None and self.handles is None and self.curve is None \
                and self.points is None:
            raise ValueError("expected one of handle, handles, curve, points")
        if not self.regions.fixed and (self.handle or self.handles or self.curve):
            raise ValueError("regions.fixed: required with a handle or curve (optional only "
                             "for a points: edit alone)")
        if self.handle is not None and not self.regions.handle:
            raise ValueError("regions.handle: required with a handle edit")
        if self.curve is not None and self.regions.handle:
            raise ValueError("regions.handle: not used by a curve edit (the curve band moves)")
        if self.curve is not None and len(self.curve.moved_to) != len(self.curve.control_points):
            raise ValueError(f"curve.moved_to: expected {len(self.curve.control_points)} points "
                             f"(one per control point), got {len(self.curve.moved_to)}")
        return self


def input_paths(cfg: EditConfig, base_dir: str | Path) -> list[tuple[str, Path]]:
    """(label, path) of every file an edit reads: the input model and the indices files its
    regions name (paths relative to ``base_dir``, the config's folder)."""
    base_dir = Path(base_dir)
    found = [("input model", base_dir / cfg.input)]
    groups = [("regions.fixed", cfg.regions.fixed), ("regions.handle", cfg.regions.handle or [])]
    for i, h in enumerate(getattr(cfg, "handles", None) or []):
        groups.append((f"handles[{i}].region", getattr(h, "region", None) or []))
    from splatdeform.edit.selectors import leaves

    points = getattr(cfg, "points", None)
    for key in ("pairs", "check_pairs"):
        value = getattr(points, key, None)
        if isinstance(value, PairsFileCfg):
            found.append((f"points.{key}.file", base_dir / value.file))
    for key, selectors in groups:
        for j, sel in enumerate(selectors):
            plain = sel.to_selector()
            for leaf in leaves(plain):   # nested in all / not too
                file = getattr(leaf, "file", None)  # selectors that read a file
                if file is not None:
                    name = _selector_name(sel) if leaf is plain else "indices"
                    found.append((f"{key}[{j}].{name}.file", base_dir / file))
    return found


def _selector_name(entry: BaseModel) -> str:
    return next(iter(type(entry).model_fields))


def _config_fields(roots: tuple[type[BaseModel], ...]) -> frozenset[str]:
    """Every field name of the config models derived from ``roots``: the only strings a key
    path is made of."""
    names, todo = set(), list(roots)
    while todo:
        cls = todo.pop()
        names.update(f.alias or n for n, f in cls.model_fields.items())  # 'in', 'not'
        todo.extend(cls.__subclasses__())
    return frozenset(names)


def _loc(loc: tuple[Any, ...], kind: str, roots: tuple[type[BaseModel], ...]) -> str:
    """The key path of a pydantic error location, from structured data: list indices and the
    config models' own field names are kept; anything else pydantic puts in ``loc`` (the
    labels of union members) is not a key. The last part of an unknown-key error is the
    unknown key itself."""
    fields = _config_fields(roots)
    out = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in fields or (kind == "extra_forbidden" and i == len(loc) - 1):
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _message(err: dict[str, Any]) -> str:
    kind = err["type"]
    if kind == "extra_forbidden":
        return "unknown key"
    if kind == "missing":
        return "required key is missing"
    raised = (err.get("ctx") or {}).get("error")  # a validator's own exception, as raised
    msg = str(raised) if kind == "value_error" and raised is not None else err["msg"]
    got = err.get("input")
    if kind not in ("value_error",) and not isinstance(got, (dict, list)):
        msg += f" (got {shown(got)})"
    return msg


def validation_error(source: str, exc: ValidationError, prefix: str = "",
                     roots: tuple[type[BaseModel], ...] = ()) -> ConfigError:
    """A ConfigError (file, key path, message) for the most specific validation error;
    ``roots``: base classes of the config models validated (default: the edit config's)."""
    errors = exc.errors()
    # prefer errors that are not union-branch noise: the deepest location first
    err = max(errors, key=lambda e: (e["type"] != "model_type", len(e["loc"]),
                                     e["type"] == "extra_forbidden"))  # 'mins' over 'min'
    loc = _loc(err["loc"], err["type"], roots or (_Strict,))
    path = f"{prefix}.{loc}" if prefix and loc != "(top level)" else (prefix or loc)
    from splatdeform.edit.hints import hint  # did you mean: the allowed keys / values

    return ConfigError.at(path, _message(err) + hint(err, exc.title, roots or (_Strict,)),
                          file=source)


def parse_edit(data: dict[str, Any], source: str, prefix: str = "") -> EditConfig:
    """Validate an edit mapping (``prefix`` names where it sits, e.g. 'edit' in a batch)."""
    try:
        return EditConfig.model_validate(data)
    except ValidationError as exc:
        raise validation_error(source, exc, prefix) from None


def load_edit(path: str | Path) -> EditConfig:
    """Read and validate an edit config file.

    Parameters
    ----------
    path : str or Path
        The edit YAML (see the edit config reference).

    Returns
    -------
    EditConfig
        The validated config; errors are one ConfigError line naming the file and key path.

    Examples
    --------
    >>> from pathlib import Path
    >>> import splatdeform as sd
    >>> _ = Path("bend.yaml").write_text('''
    ... input: bar.ply
    ... output: bar_bent.ply
    ... regions: {units: relative, fixed: [{box: {min: [0, 0, 0], max: [0.25, 1, 1]}}],
    ...           handle: [{box: {min: [0.75, 0, 0], max: [1, 1, 1]}}]}
    ... handle: {transform: {rotate: {axis: [0, 0, 1], degrees: 35}}}
    ... ''')
    >>> cfg = sd.load_edit("bend.yaml")
    >>> cfg.regions.units, cfg.handle.transform.rotate.degrees, cfg.fit.method
    ('relative', 35.0, 'auto')
    """
    return parse_edit(read_yaml(path), str(path))
