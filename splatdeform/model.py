"""The one data type for every input: :class:`PointModel`.

A model holds the geometry the deformation needs as plain numpy arrays (positions, normals, surfel
radius or tangent axes, 3D Gaussian splat fields, faces) plus, when it came from a PLY file, the
verbatim file contents (:class:`PlySource`) so that a save reproduces every property, extra
element, comment and type of the input.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import InputError

# |coordinate| beyond which a model is refused for editing (the fit's r^3 terms and its
# normalisation lose every digit; float32's 3.4e38 overflows) and a LAS header is corrupt
MAX_COORDINATE = 1e15
# a scale factor (handle scales, ``convert --scale``) outside this by magnitude is degenerate:
# it collapses the model to a point or throws it past every float32 coordinate
MIN_SCALE, MAX_SCALE = 1e-6, 1e6
KINDS = ("mesh", "oriented_cloud", "cloud", "surfel_radius", "surfel_axes", "gaussians")


# 3DGS colour: the data's own convention, so loaders, renderer and editor share one conversion
SH_C0 = 0.28209479177387814  # the degree-0 real SH constant: colour = 0.5 + SH_C0 * f_dc


def dc_to_rgb(sh_dc: np.ndarray) -> np.ndarray:
    """(N, 3) 3DGS DC coefficients -> (N, 3) float64 linear colour 0.5 + SH_C0 * f_dc
    (unclipped: the renderer clips after adding the view-dependent bands)."""
    return 0.5 + SH_C0 * np.asarray(sh_dc, dtype=np.float64)


def dc_to_colors(sh_dc: np.ndarray) -> np.ndarray:
    """(N, 3) 3DGS DC coefficients -> (N, 3) uint8 colours (clipped, rounded to nearest): the
    one conversion the loader, the renderer and the editor share."""
    return np.clip(np.round(dc_to_rgb(sh_dc) * 255.0), 0, 255).astype(np.uint8)



@dataclass
class Gaussians:
    """3D Gaussian splat fields in the usual 3DGS file conventions.

    scale_log: (N, 3) float32, log of the per-axis standard deviations.
    rotation:  (N, 4) float32, quaternion (w, x, y, z), not necessarily normalised.
    opacity:   (N,) float32 logit, or None.
    sh_dc:     (N, 3) float32 degree-0 SH coefficients, or None.
    sh_rest:   (N, M) float32 higher SH coefficients (f_rest_*, channel-major), or None.

    As loaded, the fields are read-only views of the model's source rows (no second copy);
    edit ``PointModel.copy()`` (as ``deform.apply`` does).
    """

    scale_log: np.ndarray
    rotation: np.ndarray
    opacity: np.ndarray | None = None
    sh_dc: np.ndarray | None = None
    sh_rest: np.ndarray | None = None


@dataclass
class PlyProperty:
    """One PLY property as written in the header.

    dtype / len_dtype: numpy type codes ('f4', 'u1', ...); type_name / len_type_name: the
    spelling used in the file ('float', 'float32', 'uchar', ...), written back unchanged.
    """

    name: str
    dtype: str
    type_name: str
    is_list: bool = False
    len_dtype: str = ""
    len_type_name: str = ""


@dataclass
class AsciiRows:
    """The body rows of one ascii PLY element as read.

    body: the rows' bytes; starts: (R + 1,) int64 offset of each row in ``body`` (row i is
    body[starts[i]:starts[i + 1]], without its newline); original: the data parsed from them
    (the same array object the reader returned, never modified in place).
    """

    body: bytes
    starts: np.ndarray
    original: np.ndarray


@dataclass
class PlyElementData:
    """One PLY element: its properties and its rows.

    data: (count,) structured array; scalar properties are plain fields, list properties are
    object fields holding one 1-D array per row (the plyfile convention).
    ascii_text: for an element read from an ascii file, its rows as read (AsciiRows), so a save
    keeps the original text of every value that did not change; None otherwise.
    """

    name: str
    properties: list[PlyProperty]
    data: np.ndarray
    ascii_text: AsciiRows | None = None

    @property
    def count(self) -> int:
        return int(self.data.shape[0])

    def property(self, name: str) -> PlyProperty | None:
        for prop in self.properties:
            if prop.name == name:
                return prop
        return None


@dataclass
class PlySource:
    """Everything a PLY file held, kept verbatim for a lossless save.

    elements: in file order; comments / obj_info: header lines in order; text: ascii format;
    byte_order: '<' or '>' for binary files. quantised: the quantised file this source was
    decoded from (a PlayCanvas compressed PlySource, or a SOG's codes), so a re-quantising save
    keeps the codes of untouched chunks or splats; None otherwise.
    """

    elements: list[PlyElementData]
    comments: list[str] = field(default_factory=list)
    obj_info: list[str] = field(default_factory=list)
    text: bool = False
    byte_order: str = "<"
    quantised: PlySource | object | None = None

    def element(self, name: str) -> PlyElementData | None:
        for element in self.elements:
            if element.name == name:
                return element
        return None


@dataclass
class PointModel:
    """A scanned point model.

    Parameters
    ----------
    positions : array_like, shape (N, 3)
        Point positions, stored as float64.
    normals : ndarray of float64, shape (N, 3), optional
        Unit normals.
    colors : ndarray of uint8, shape (N, 3), optional
        RGB colours.
    radius : ndarray of float64, shape (N,), optional
        Surfel radii.
    axes : ndarray of float64, shape (N, 2, 3), optional
        Surfel/splat tangent axes (u, v).
    faces : ndarray of int64, shape (F, 3), optional
        Triangles (from ``face`` lists, fan-triangulated, or ``tristrips``).
    gaussians : Gaussians, optional
        3DGS fields.
    kind : str
        One of :data:`KINDS`.
    source : PlySource, optional
        The verbatim PLY contents (None for models not read from PLY).
    path : str, optional
        The file it was loaded from, if any (saves refuse to overwrite it).

    Returns
    -------
    PointModel
        The model; :func:`load` and ``data_tools.synth`` make them from files and seeds.

    Raises
    ------
    InputError
        ``positions`` not of shape (N, 3).

    Examples
    --------
    >>> import splatdeform as sd
    >>> from data_tools.synth import bumpy_bar, gaussian_bar
    >>> tri = sd.PointModel(positions=[[0, 0, 0], [1, 0, 0], [0, 2, 0]])
    >>> tri.n_points, tri.kind, tri.positions.dtype, tri.diagonal()
    (3, 'cloud', dtype('float64'), 2.23606797749979)
    >>> bar = bumpy_bar(2000)
    >>> bar.kind, bar.normals.shape, bar.radius.shape
    ('surfel_radius', (2000, 3), (2000,))
    >>> splats = gaussian_bar(500)
    >>> splats.kind, splats.gaussians.rotation.shape
    ('gaussians', (500, 4))
    """

    positions: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    radius: np.ndarray | None = None
    axes: np.ndarray | None = None
    faces: np.ndarray | None = None
    gaussians: Gaussians | None = None
    kind: str = "cloud"
    source: PlySource | None = None
    path: str | None = None

    def __post_init__(self) -> None:
        self.positions = np.asarray(self.positions, dtype=np.float64)
        if self.positions.ndim != 2 or self.positions.shape[1] != 3:
            raise InputError(f"positions: expected shape (N, 3), got {self.positions.shape}")

    @property
    def n_points(self) -> int:
        return int(self.positions.shape[0])

    @property
    def n_faces(self) -> int:
        return 0 if self.faces is None else int(self.faces.shape[0])

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box: two (3,) float64 arrays (min, max)."""
        from splatdeform.geometry import bounds

        return bounds(self.positions)

    def diagonal(self) -> float:
        """Length of the bounding-box diagonal (model units)."""
        lo, hi = self.bbox()
        return float(np.linalg.norm(hi - lo))

    def copy(self) -> PointModel:
        """Deep copy of the per-point arrays (the verbatim source is shared, it is read-only)."""

        def c(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a.copy()

        g = self.gaussians
        gaussians = (
            None
            if g is None
            else Gaussians(c(g.scale_log), c(g.rotation), c(g.opacity), c(g.sh_dc), c(g.sh_rest))
        )
        return replace(
            self,
            positions=self.positions.copy(),
            normals=c(self.normals),
            colors=c(self.colors),
            radius=c(self.radius),
            axes=c(self.axes),
            faces=c(self.faces),
            gaussians=gaussians,
        )


def classify(
    *,
    has_faces: bool,
    has_normals: bool,
    has_radius: bool,
    has_axes: bool,
    has_gaussians: bool,
) -> str:
    """The model kind from what it holds (3DGS > surfels > mesh > oriented > plain cloud)."""
    if has_gaussians:
        return "gaussians"
    if has_axes:
        return "surfel_axes"
    if has_radius:
        return "surfel_radius"
    if has_faces:
        return "mesh"
    if has_normals:
        return "oriented_cloud"
    return "cloud"


def vertex_column(model: PointModel, name: str, what: str = "property") -> np.ndarray:
    """(N,) the scalar vertex property ``name`` of ``model`` (a PLY property or a decoded LAS
    dimension); InputError naming ``what`` (the config key or option), the file and the
    properties it has otherwise."""
    vertex = None if model.source is None else model.source.element("vertex")
    names = () if vertex is None else vertex.data.dtype.names or ()
    if name not in names:
        where = f"{model.path}: " if model.path else ""
        raise InputError(f"{where}{what}: no vertex property {name!r} (the file has "
                         f"{', '.join(names) or 'none'})")
    column = vertex.data[name]
    if column.ndim != 1:
        raise InputError(f"{what}: {name!r} is not a scalar property")
    return column
