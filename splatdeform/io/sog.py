"""PlayCanvas SOG (version 2): ``meta.json`` plus 8-bit WebP images, bundled as a ZIP (``.sog``)
or as a folder (a ``meta.json`` with its images beside it), from the format's specification.

Per splat, pixel i (row-major, top-left origin) of every per-splat image:
positions: 16 bits per axis (``means_u`` high byte, ``means_l`` low byte, RGB = x y z) of the
symmetric log n = sign(p) ln(1 + |p|) between ``means.mins`` and ``means.maxs``;
rotation (``quats``): smallest-three, RGB the kept components as c / 255 in [-1/sqrt2, 1/sqrt2]
(c = (v sqrt2 / 2 + 0.5) * 255), A = 252 + the index (w x y z) of the dropped largest one;
log scales (``scales``, RGB): indices into a 256-entry codebook; ``sh0``: RGB indices into a
256-entry codebook of f_dc, A the opacity after the sigmoid (a / 255); SH rest (``shN``): a
16-bit palette label (``shN_labels`` R + 256 G) and a palette image of 64 entries per row, each
entry K pixels (one per coefficient) whose RGB index a third 256-entry codebook.
The codebooks are seeded, deterministic k-means (:mod:`.kmeans`); the images are written as
lossless, exact WebP (Pillow) so the stored codes are the codes. The writers store the splats
in Morton order (:mod:`.sog_order`; ``sog_order: keep``: the given order), as splat-transform
does: a scene read back comes in that order.

Axes: the SOG specification states x right, y up, z back; the pinned splat-transform writes and
reads SOG in PLY space (no flip; a PLY converted to SOG and back keeps its coordinates), and a
reader cannot tell the two apart, so SOG is read and written in PLY space (as splat-transform).
"""

from __future__ import annotations

import io
import json
import math
import warnings
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError, InputError
from ..model import PointModel
from .inflate import check_declared, inflate_zip_member
from .kmeans import codebook_1d, kmeans_rows
from .regular import member_path, open_regular, read_regular
from .splat_model import to_model
from .splats import (
    SH_COEFFS,
    SplatFields,
    alpha_logit,
    fields_of,
    normalised_quaternions,
    note_lossy,
    restore_largest,
)
from .spz import PLAUSIBLE_RATIO, PLAUSIBLE_SLACK

VERSION = 2
CODEBOOK = 256
PALETTE_ROW = 64
MAX_PALETTE = 65536  # the format's limit (16-bit labels)
PALETTE_CAP = 4096  # the fast encoder's most entries: the k-means cost grows with N x entries
#: SH encoders: ``reference`` (the default) sizes the palette as the reference encoder
#: (splat-transform: 1024 x 2^floor(log2(N / 1024)) entries, at most 65536, so about N / 1.5 to
#: N / 3 entries; SH error about that encoder's, file about its size, k-means cost ~N^2 / 2);
#: ``fast``: a power of two near N / 16, at most 4096 (measured, files in Morton order: 2.4x the
#: SH RMS error, 2.8x the mean absolute, 0.47x the file on the 6.8k-splat SH3 test tile; 1.5x,
#: 1.8x, 0.48x and 8.9 s against ~270 s on a generated 150k-splat SH3 scene: scenes with more
#: varied SH lose more)
QUALITIES = ("reference", "fast")
_QUALITY: ContextVar[str] = ContextVar("sog_quality", default="reference")
MAX_META = 16 << 20  # bytes of a meta.json (a few codebooks: tens of kilobytes)
MAX_PIXELS = 1 << 28  # WebP's 16383 x 16383
IMAGE_FORMATS = ("WEBP", "PNG")
FLOAT32_MAX = float(np.finfo(np.float32).max)
# positions are stored as sign(p) ln(1 + |p|): a bound past ln(float32 max) ~ 88.7 decodes to
# infinity in the float32 table
MAX_LOG_POSITION = 88.0
# bytes a decode holds per splat (the RGBA images, the codes, float fields, the model's table)
# and per SH rest coefficient: what the memory cap is checked against before reading images
DECODED_PER_SPLAT = 320
#: pixel bytes a splat takes in the five per-splat RGBA images (means_l, means_u, quats, scales,
#: sh0): held, like an SPZ stream, to at most PLAUSIBLE_RATIO x the stored bytes (+ slack)
PIXEL_BYTES = 20
DECODED_PER_COEFF = 48
SEED = 0
LOSSES = ("positions 16 bits per axis (log-spaced), rotation 8 bits per component, log "
          "scales and colour through 256-entry k-means codebooks, opacity 8 bits, SH rest "
          "through a k-means palette (the reference encoder's size, or at most 4096 entries with "
          "sog_quality fast) of 256 codebook values")
FILES = {"means": ["means_l.webp", "means_u.webp"], "scales": ["scales.webp"],
         "quats": ["quats.webp"], "sh0": ["sh0.webp"],
         "shN": ["shN_centroids.webp", "shN_labels.webp"]}


@dataclass
class SogCodes:
    """The stored codes of one SOG scene (what a re-write keeps for untouched splats).

    means: (N, 3) uint16; quats: (N, 4) uint8; scales: (N, 3) uint8; sh0: (N, 4) uint8;
    labels: (N,) int64 or None; centroids: (P, K, 3) uint8 or None; meta: the meta.json dict.
    """

    meta: dict
    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    sh0: np.ndarray
    labels: np.ndarray | None = None
    centroids: np.ndarray | None = None


# --------------------------------------------------------------------------------------------
# containers


class _Files:
    """The SOG members by name: a ZIP bundle's entries or the files beside a meta.json. Every
    read is bounded: a bundle's member by its declared size (checked against what the caller
    allows before inflating, then inflated a chunk at a time), a folder's member through the one
    opener (a regular file inside the meta.json's folder, refused above what the caller
    allows)."""

    def __init__(self, path: Path):
        self.path = path
        self.zip: zipfile.ZipFile | None = None
        self._fh = None
        if path.suffix.lower() == ".sog":
            self._fh = open_regular(path, what="SOG bundle")
            try:
                self.zip = zipfile.ZipFile(self._fh)
            except (zipfile.BadZipFile, OSError, EOFError, ValueError,
                    NotImplementedError) as exc:   # e.g. a flipped "version needed" byte
                self._fh.close()
                raise FormatError(f"{path}: not a SOG bundle (a ZIP archive expected): "
                                  f"{exc}") from None

    def read(self, name: str, max_bytes: int, what: str = "SOG member") -> bytes | bytearray:
        """The member ``name``, refused (one line) when it holds more than ``max_bytes``."""
        if not isinstance(name, str) or not name or "/" in name or "\\" in name or \
                "\x00" in name or name.startswith("."):
            raise FormatError(f"{self.path}: SOG file name {name!r} is not a plain file name")
        try:
            if self.zip is not None:
                info = self.zip.getinfo(name)
                return inflate_zip_member(self.zip, info, max_bytes, what, self.path)
            member = member_path(self.path, name, f"SOG file {name}")
            return read_regular(member, max_bytes=max_bytes, inside=self.path.parent,
                                what=f"{what} of {self.path}")
        except KeyError:
            raise FormatError(f"{self.path}: the SOG bundle has no {name}") from None
        except FileNotFoundError:
            raise FormatError(f"{self.path}: the SOG file {name} is missing beside it") from None
        except PermissionError:
            raise FormatError(f"{self.path}: cannot read the SOG file {name} (permission "
                              "denied)") from None
        except (zipfile.BadZipFile, OSError, EOFError, ValueError, RuntimeError,
                NotImplementedError) as exc:
            if isinstance(exc, InputError):
                raise
            raise FormatError(f"{self.path}: cannot read SOG member {name}: {exc}") from None

    def close(self) -> None:
        if self.zip is not None:
            self.zip.close()
        if self._fh is not None:
            self._fh.close()


def _meta(path: Path, files: _Files) -> dict:
    raw = files.read("meta.json", MAX_META) if files.zip is not None else \
        read_regular(path, max_bytes=MAX_META, what="SOG meta.json")
    try:
        meta = json.loads(raw)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise FormatError(f"{path}: SOG meta.json is not valid JSON: {exc}") from None
    if not isinstance(meta, dict) or "means" not in meta:
        raise FormatError(f"{path}: not a SOG meta.json (no 'means' entry)")
    if meta.get("version") != VERSION:
        raise FormatError(f"{path}: SOG version {meta.get('version')!r} is not supported "
                          f"(version {VERSION} is)")
    count = meta.get("count")
    if not isinstance(count, int) or isinstance(count, bool) or not 1 <= count <= MAX_PIXELS:
        raise FormatError(f"{path}: SOG meta.json count {count!r}; expected a positive integer "
                          f"of at most {MAX_PIXELS:,} (what an image can hold)")
    shn = meta.get("shN")
    bands = shn.get("bands") if isinstance(shn, dict) else None
    k = SH_COEFFS.get(bands, 0) if isinstance(bands, int) else 0
    check_declared(path, f"SOG meta.json ({count:,} splats)", count,
                   decoded=count * (DECODED_PER_SPLAT + DECODED_PER_COEFF * k))
    stored = _stored_bytes(path, files, meta, len(raw))
    if count * PIXEL_BYTES > PLAUSIBLE_RATIO * stored + PLAUSIBLE_SLACK:
        raise FormatError(f"{path}: SOG meta.json declares {count:,} splats "
                          f"({count * PIXEL_BYTES:,} bytes of pixels) in {stored:,} stored "
                          "bytes; splat data compresses "
                          f"at most {PLAUSIBLE_RATIO}x (+{PLAUSIBLE_SLACK >> 20} MiB) here: "
                          "refused before decoding its images")
    return meta


def _stored_bytes(path: Path, files: _Files, meta: dict, meta_bytes: int) -> int:
    """The bytes the scene is stored in: a bundle's members as compressed, or meta.json and the
    plain-named files its entries list beside it (those that exist)."""
    if files.zip is not None:
        return sum(info.compress_size for info in files.zip.infolist())
    total = meta_bytes
    for key in FILES:
        entry = meta.get(key)
        names = entry.get("files") if isinstance(entry, dict) else None
        for name in names if isinstance(names, list) else ():
            if isinstance(name, str) and name and "/" not in name and "\\" not in name \
                    and "\x00" not in name and not name.startswith("."):
                try:
                    total += (path.parent / name).stat().st_size
                except OSError:
                    continue
    return total


def _entry(path: Path, meta: dict, key: str, files: int) -> dict:
    entry = meta.get(key)
    if not isinstance(entry, dict) or not isinstance(entry.get("files"), list) or \
            len(entry["files"]) != files:
        raise FormatError(f"{path}: SOG meta.json '{key}' needs a 'files' list of {files}")
    return entry


def _floats(path: Path, entry: dict, key: str, name: str, size: int,
            limit: float = FLOAT32_MAX) -> np.ndarray:
    """``size`` finite numbers of magnitude at most ``limit`` (default: what float32 holds, so
    a codebook value cannot become infinite when stored)."""
    value = entry.get(name)
    try:
        out = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        out = np.zeros(0)
    if out.shape != (size,) or not np.isfinite(out).all() or (np.abs(out) > limit).any():
        raise FormatError(f"{path}: SOG meta.json '{key}.{name}' must be {size} finite numbers "
                          f"of magnitude at most {limit:.6g}")
    return out


def splat_image_fits(width: int, height: int, count: int) -> bool:
    """True when a per-splat image of ``width`` x ``height`` is laid out for ``count`` splats
    as the format's writers lay it out: row-major, at least ``count`` pixels, at most 4 rows
    more than ``count`` needs at that width (splat-transform: a width of sqrt(count) rounded up
    to a multiple of 4 and the height rounded up to a multiple of 4; this writer: the height
    just enough), and a width no longer than the count needs. Checked from the header, before
    decoding, so a small file cannot declare an 8000x8000 image for a few splats (the area is
    below 6 x count + 96 whatever the width)."""
    if width < 1 or height < 1 or width > count + 16:
        return False
    return width * height >= count and height <= -(-count // width) + 4


def max_image_bytes(pixels: int) -> int:
    """The most bytes an 8-bit RGBA image of ``pixels`` pixels can take as a (lossless) WebP or
    PNG: its raw size with room for the container and incompressible data."""
    return 5 * pixels + (1 << 16)


def _image(path: Path, files: _Files, name: str, max_pixels: int, fits, expect: str
           ) -> np.ndarray:
    """(H, W, 4) uint8 of one WebP (or PNG) member: its byte size is bounded by
    ``max_pixels`` before it is read, and its declared dimensions (the header, read without
    decoding) must pass ``fits(width, height)`` (``expect`` says what was expected) before it is
    decoded."""
    from PIL import Image

    raw = files.read(name, max_image_bytes(max_pixels), "SOG image")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            img = Image.open(io.BytesIO(raw), formats=IMAGE_FORMATS)
        with img:
            width, height = img.size
            if width * height > MAX_PIXELS or not fits(width, height):
                raise FormatError(f"{path}: SOG image {name} is {width}x{height}: "
                                  f"{width * height:,} pixels for {expect}")
            rgba = np.asarray(img.convert("RGBA"))
    except FormatError:
        raise
    except (OSError, ValueError, SyntaxError, EOFError, Image.DecompressionBombError) as exc:
        raise FormatError(f"{path}: SOG image {name} cannot be decoded: {exc}") from None
    if rgba.shape[:2] != (height, width):
        raise FormatError(f"{path}: SOG image {name} decodes to {rgba.shape[1]}x"
                          f"{rgba.shape[0]}, not the {width}x{height} its header declares")
    return rgba


def _per_splat(path: Path, files: _Files, name: str, n: int) -> np.ndarray:
    rgba = _image(path, files, name, 6 * n + 96,
                  lambda w, h: splat_image_fits(w, h, n),
                  f"{n:,} splats (expected at least {n:,} pixels, padded by at most 4 rows)")
    return rgba.reshape(-1, 4)[:n]


# --------------------------------------------------------------------------------------------
# decoding


def unlog(n: np.ndarray) -> np.ndarray:
    return np.sign(n) * np.expm1(np.abs(n))


def quats_from_codes(codes: np.ndarray) -> np.ndarray:
    """(N, 4) uint8 RGBA -> (N, 4) float64 w x y z."""
    kept = (codes[:, :3].astype(np.float64) / 255 - 0.5) * math.sqrt(2.0)
    return restore_largest(kept, codes[:, 3].astype(np.intp) - 252)


def decode(path: str | Path) -> tuple[SplatFields, SogCodes]:
    """The splat fields (PLY space) and the stored codes of a SOG bundle or meta.json."""
    path = Path(path)
    files = _Files(path)
    try:
        meta = _meta(path, files)
        n = meta["count"]
        means = _entry(path, meta, "means", 2)
        mins = _floats(path, means, "means", "mins", 3, MAX_LOG_POSITION)
        maxs = _floats(path, means, "means", "maxs", 3, MAX_LOG_POSITION)
        lo = _per_splat(path, files, means["files"][0], n)[:, :3].astype(np.uint16)
        hi = _per_splat(path, files, means["files"][1], n)[:, :3].astype(np.uint16)
        q16 = (hi << np.uint16(8)) | lo
        positions = unlog(mins + (maxs - mins) * (q16.astype(np.float64) / 65535))
        quats = _per_splat(path, files, _entry(path, meta, "quats", 1)["files"][0], n)
        if not np.isin(quats[:, 3], (252, 253, 254, 255)).all():
            raise FormatError(f"{path}: SOG quats alpha outside 252..255 (the reserved modes)")
        entry = _entry(path, meta, "scales", 1)
        book = _floats(path, entry, "scales", "codebook", CODEBOOK).astype(np.float32)
        scales = _per_splat(path, files, entry["files"][0], n)
        entry = _entry(path, meta, "sh0", 1)
        dc_book = _floats(path, entry, "sh0", "codebook", CODEBOOK).astype(np.float32)
        sh0 = _per_splat(path, files, entry["files"][0], n)
        codes = SogCodes(meta=meta, means=q16, quats=quats.copy(), scales=scales[:, :3].copy(),
                         sh0=sh0.copy())
        rest = np.zeros((n, 3, 0), np.float32)
        if "shN" in meta:
            rest = _sh_rest(path, files, meta, n, codes)
    finally:
        files.close()
    fields = SplatFields(positions=positions, scale_log=book[scales[:, :3]],
                         rotation=quats_from_codes(quats).astype(np.float32),
                         opacity=alpha_logit(sh0[:, 3] / 255).astype(np.float32),
                         sh_dc=dc_book[sh0[:, :3]], sh_rest=rest)
    return fields, codes


def _sh_rest(path: Path, files: _Files, meta: dict, n: int, codes: SogCodes) -> np.ndarray:
    entry = _entry(path, meta, "shN", 2)
    bands, count = entry.get("bands"), entry.get("count")
    if bands not in (1, 2, 3) or not isinstance(count, int) or not 1 <= count <= MAX_PALETTE:
        raise FormatError(f"{path}: SOG shN needs bands 1..3 and count 1..{MAX_PALETTE} "
                          f"(got {bands!r}, {count!r})")
    k = SH_COEFFS[bands]
    book = _floats(path, entry, "shN", "codebook", CODEBOOK).astype(np.float32)
    rows = -(-count // PALETTE_ROW)
    palette = _image(path, files, entry["files"][0], PALETTE_ROW * k * (rows + 4),
                     lambda w, h: w == PALETTE_ROW * k and rows <= h <= rows + 4,
                     f"a palette of {count} entries of {k} coefficients (expected "
                     f"{PALETTE_ROW * k}x{rows})")
    centroids = palette[:rows, :PALETTE_ROW * k, :3].reshape(-1, k, 3)[:count]
    label_px = _per_splat(path, files, entry["files"][1], n)
    labels = label_px[:, 0].astype(np.int64) | (label_px[:, 1].astype(np.int64) << 8)
    if labels.max() >= count:
        raise FormatError(f"{path}: SOG shN label {int(labels.max())} outside the "
                          f"{count}-entry palette")
    codes.labels, codes.centroids = labels, centroids.copy()
    # the palette's values in PLY's channel-major f_rest order (P, 3, K), then one gather
    values = np.ascontiguousarray(book[centroids].transpose(0, 2, 1))
    return values[labels]


def read_info(path: str | Path) -> dict:
    path = Path(path)
    files = _Files(path)
    try:
        meta = _meta(path, files)
    finally:
        files.close()
    shn = meta.get("shN") if isinstance(meta.get("shN"), dict) else {}
    return {"version": meta["version"], "count": meta["count"],
            "sh_bands": shn.get("bands", 0), "palette": shn.get("count", 0),
            "antialias": bool(meta.get("antialias", False)),
            "generator": (meta.get("asset") or {}).get("generator", "?")
            if isinstance(meta.get("asset"), dict) else "?"}


def read_model(path: str | Path, *, drop_nonfinite: bool = False) -> PointModel:
    fields, codes = decode(path)
    model = to_model(fields, path, ["read from a PlayCanvas SOG by splatdeform"],
                     drop_nonfinite=drop_nonfinite)
    if model.source is not None:
        model.source.quantised = codes  # a re-write keeps the untouched splats' codes
    return model


# --------------------------------------------------------------------------------------------
# encoding


def log_transform(p: np.ndarray) -> np.ndarray:
    return np.sign(p) * np.log1p(np.abs(p))


def quat_codes(q_wxyz: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions -> (N, 4) uint8 RGBA smallest-three codes."""
    q = normalised_quaternions(q_wxyz)
    n = len(q)
    largest = np.argmax(np.abs(q), axis=1)
    q *= np.where(q[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]
    keep = np.ones((n, 4), dtype=bool)
    keep[np.arange(n), largest] = False
    others = q[keep].reshape(n, 3)
    out = np.empty((n, 4), dtype=np.uint8)
    out[:, :3] = np.clip(np.round((others / math.sqrt(2.0) + 0.5) * 255), 0, 255)
    out[:, 3] = 252 + largest
    return out


def _size(n: int) -> tuple[int, int]:
    """(width, height) of the per-splat images: a multiple-of-4 width near sqrt(n)."""
    width = max(4, -(-math.ceil(math.sqrt(n)) // 4) * 4)
    return width, -(-n // width)


def _webp(pixels: np.ndarray, width: int, height: int, effort: int) -> bytes:
    """Lossless, exact WebP of (M, 4) uint8 pixels (padded with zeros to width x height)."""
    from PIL import Image

    full = np.zeros((width * height, 4), dtype=np.uint8)
    full[:len(pixels), :pixels.shape[1]] = pixels
    if pixels.shape[1] < 4:
        full[:, 3] = 255
    buf = io.BytesIO()
    Image.fromarray(full.reshape(height, width, 4), "RGBA").save(
        buf, "WEBP", lossless=True, exact=True, quality=effort, method=min(6, effort // 17))
    return buf.getvalue()


@contextmanager
def quality(name: str | None) -> Iterator[None]:
    """SOG writes inside the block use the SH encoder ``name`` (one of :data:`QUALITIES`;
    None: the default, ``reference``)."""
    if name is not None and name not in QUALITIES:
        raise InputError(f"sog_quality: expected one of {', '.join(QUALITIES)}, got {name!r}")
    token = _QUALITY.set(name or "reference")
    try:
        yield
    finally:
        _QUALITY.reset(token)


def _palette_size(n: int, mode: str = "fast") -> int:
    """SH palette entries for ``n`` splats. ``reference``: 1024 x 2^floor(log2(n / 1024)),
    capped at 64 x 1024 (the reference encoder's rule; below 1024 splats a fraction of 1024);
    ``fast``: a power of two near n / 16, 64 .. PALETTE_CAP."""
    if mode == "reference":
        return int(max(1, min(64, 2.0 ** math.floor(math.log2(max(n, 1) / 1024))) * 1024))
    return int(min(PALETTE_CAP, max(64, 2 ** round(math.log2(max(n, 1) / 16)))))


def encode(f: SplatFields, *, keep: SogCodes | None = None, same: np.ndarray | None = None,
           iterations: int = 10, effort: int = 75, sh_quality: str | None = None
           ) -> dict[str, bytes]:
    """The SOG members (``meta.json`` and the images) of ``f``, splats in their given order.
    ``sh_quality``: the SH encoder (:data:`QUALITIES`; None: the :func:`quality` in force).

    keep/same: the codes of the scene the fields were read from and (N,) bool of the splats
    still holding their decoded values: those splats keep their codes, and the codebook entries
    and palette entries they use keep their index and value (the k-means fits the other
    entries to the changed splats)."""
    n = f.count
    width, height = _size(n)
    reuse = keep is not None and same is not None and same.any()
    meta: dict = {"version": VERSION, "asset": {"generator": "splatdeform"}, "count": n,
                  "antialias": bool(keep.meta.get("antialias", False)) if keep else False}
    out: dict[str, bytes] = {}
    # positions
    logp = log_transform(f.positions)
    mins, maxs = logp.min(axis=0), logp.max(axis=0)
    if n and np.abs(logp).max() > MAX_LOG_POSITION:
        top = float(np.abs(f.positions).max())
        raise FormatError(f"a coordinate of magnitude {top:g} does not fit SOG (positions are "
                          f"stored as ln(1 + |p|), at most {MAX_LOG_POSITION:g}: "
                          f"|p| <= {math.expm1(MAX_LOG_POSITION):.3g})")
    if reuse:
        old_min = np.asarray(keep.meta["means"]["mins"], dtype=np.float64)
        old_max = np.asarray(keep.meta["means"]["maxs"], dtype=np.float64)
        # the untouched splats keep their codes: only the others must fit the old range (a
        # decoded position can round a hair outside it)
        moved = logp[~same]
        if not len(moved) or ((moved.min(axis=0) >= old_min).all() and
                              (moved.max(axis=0) <= old_max).all()):
            mins, maxs = old_min, old_max
    span = np.where(maxs > mins, maxs - mins, 1.0)
    q16 = np.clip(np.round((logp - mins) / span * 65535), 0, 65535).astype(np.uint16)
    if reuse and np.array_equal(mins, keep.meta["means"]["mins"]) and \
            np.array_equal(maxs, keep.meta["means"]["maxs"]):
        q16[same] = keep.means[same]
    meta["means"] = {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": FILES["means"]}
    out[FILES["means"][0]] = _webp((q16 & 0xFF).astype(np.uint8), width, height, effort)
    out[FILES["means"][1]] = _webp((q16 >> 8).astype(np.uint8), width, height, effort)
    # rotations
    quats = quat_codes(f.rotation)
    if reuse:
        quats[same] = keep.quats[same]
    meta["quats"] = {"files": FILES["quats"]}
    out[FILES["quats"][0]] = _webp(quats, width, height, effort)
    # log scales and sh0 through 256-entry codebooks
    scales, book = _codebook_codes(f.scale_log, keep.scales if reuse else None,
                                   _old_book(keep, "scales") if reuse else None, same)
    meta["scales"] = {"codebook": _short(book), "files": FILES["scales"]}
    out[FILES["scales"][0]] = _webp(scales, width, height, effort)
    dc, book = _codebook_codes(f.sh_dc, keep.sh0[:, :3] if reuse else None,
                               _old_book(keep, "sh0") if reuse else None, same)
    from .splats import sigmoid

    alpha = np.clip(np.round(sigmoid(f.opacity) * 255), 0, 255).astype(np.uint8)
    if reuse:
        alpha[same] = keep.sh0[same, 3]
    meta["sh0"] = {"codebook": _short(book), "files": FILES["sh0"]}
    out[FILES["sh0"][0]] = _webp(np.concatenate([dc, alpha[:, None]], axis=1), width, height,
                                 effort)
    k = f.sh_rest.shape[2]
    if k:
        shn, members = _encode_sh(f, keep if reuse and keep.labels is not None and
                                  keep.centroids.shape[1] == k else None, same, iterations,
                                  width, height, effort, sh_quality or _QUALITY.get())
        meta["shN"] = shn
        out.update(members)
    out["meta.json"] = json.dumps(meta, separators=(",", ":")).encode()
    return out


def _short(book: np.ndarray) -> list[float]:
    """A float32 codebook as the shortest decimals that read back to the same float32 values
    (a double's repr of each would take twice the text in meta.json)."""
    return [float(str(v)) for v in np.asarray(book, dtype=np.float32)]


def _old_book(keep: SogCodes, key: str) -> np.ndarray:
    return np.asarray(keep.meta[key]["codebook"], dtype=np.float32)


def _codebook_codes(values: np.ndarray, old_codes: np.ndarray | None,
                    old_book: np.ndarray | None, same: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) values -> (N, 3) uint8 codes and the (256,) float32 codebook (1-D k-means over
    every value; with old codes, the entries the unchanged rows use stay fixed)."""
    fixed = None
    data = values
    if old_codes is not None:
        used = np.unique(old_codes[same])
        fixed = old_book[used]
        data = values[~same]
    book = codebook_1d(np.asarray(data, dtype=np.float32).ravel(), CODEBOOK, fixed=fixed,
                       fill=np.asarray(values, dtype=np.float32).ravel())
    if old_codes is None:
        return nearest_1d(book, values), book
    # the kept entries stay at their old indices (same value, same code); the k-means' other
    # centres fill the free slots
    free_values = list(book)
    for value in np.unique(fixed):
        free_values.remove(value)
    final = np.empty(CODEBOOK, dtype=np.float32)
    final[used] = old_book[used]
    slots = np.setdiff1d(np.arange(CODEBOOK), used)
    final[slots] = np.sort(np.asarray(free_values, dtype=np.float32))[:len(slots)] \
        if free_values else old_book[used][0]
    codes = nearest_1d(final, values)
    codes[same] = old_codes[same]
    return codes, final


def nearest_1d(book: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Index of the nearest entry of a (256,) book (any order) for each value (uint8, the
    values' shape)."""
    values = np.asarray(values, dtype=np.float32)
    order = np.argsort(book, kind="stable")
    ordered = book[order]
    mid = (ordered[1:] + ordered[:-1]) * np.float32(0.5)
    return order[np.searchsorted(mid, values)].astype(np.uint8)


def _encode_sh(f: SplatFields, keep: SogCodes | None, same: np.ndarray | None,
               iterations: int, width: int, height: int, effort: int, mode: str = "reference"
               ) -> tuple[dict, dict[str, bytes]]:
    n, k = f.count, f.sh_rest.shape[2]
    # (N, K, 3) view: coefficient-major, rgb inside (rows of K*3 values, flattened by block)
    rows = f.sh_rest.transpose(0, 2, 1)
    palette_n = _palette_size(n, mode)
    if keep is not None:
        used = np.unique(keep.labels[same])
        palette_n = max(palette_n, min(MAX_PALETTE, len(used) + palette_n // 2))
        old_book = _old_book(keep, "shN")
        fixed_rows = old_book[keep.centroids[used]].reshape(len(used), 3 * k)
        found, labels = kmeans_rows(rows[~same], palette_n, fixed=fixed_rows,
                                    iterations=iterations, seed=SEED)
        # kept palette entries stay at their old labels; the new ones fill the free slots
        total = max(len(found), int(used.max()) + 1 if len(used) else 0)
        slot = np.empty(len(found), dtype=np.int64)
        slot[:len(used)] = used
        slot[len(used):] = np.setdiff1d(np.arange(total), used)[:len(found) - len(used)]
        centres = np.zeros((total, 3 * k), dtype=np.float32)
        centres[slot] = found
        kept = np.zeros(total, dtype=bool)
        kept[used] = True
        old_codes = np.zeros((total, 3 * k), dtype=np.uint8)
        old_codes[used] = keep.centroids[used].reshape(len(used), -1)
        all_labels = np.empty(n, dtype=np.int64)
        all_labels[~same] = slot[labels]
        all_labels[same] = keep.labels[same]
        codes, book = _codebook_codes(centres, old_codes if len(used) else None,
                                      old_book if len(used) else None, kept)
    else:
        centres, all_labels = kmeans_rows(rows, palette_n, iterations=iterations, seed=SEED)
        codes, book = _codebook_codes(centres, None, None, None)
    count = len(centres)
    grid_rows = -(-count // PALETTE_ROW)
    palette = np.zeros((grid_rows * PALETTE_ROW, k, 4), dtype=np.uint8)
    palette[:count, :, :3] = codes.reshape(count, k, 3)
    palette[:, :, 3] = 255
    members = {FILES["shN"][0]: _webp(palette.reshape(-1, 4), PALETTE_ROW * k, grid_rows,
                                      effort)}
    label_px = np.zeros((n, 2), dtype=np.uint8)
    label_px[:, 0] = all_labels & 0xFF
    label_px[:, 1] = all_labels >> 8
    members[FILES["shN"][1]] = _webp(label_px, width, height, effort)
    shn = {"count": count, "bands": {3: 1, 8: 2, 15: 3}[k], "codebook": _short(book),
           "files": FILES["shN"]}
    return shn, members


def write_model(model: PointModel, path: Path, stream) -> None:
    """Write ``model`` (3D Gaussian splats) as a SOG ZIP bundle to ``stream``, the splats in
    the order :mod:`.sog_order` sets (Morton by default)."""
    fields = fields_of(model, path, ".sog")
    note_lossy(path, ".sog", LOSSES, model)
    fields, kept = _in_order(fields, _kept(model, fields))
    members = encode(fields, **kept)
    _check_readable(path, fields.count, members)
    with zipfile.ZipFile(stream, "w", compression=zipfile.ZIP_STORED) as bundle:
        for name in ("meta.json", *[m for m in members if m != "meta.json"]):
            info = zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0))
            bundle.writestr(info, members[name])


def write_folder(model: PointModel, path: Path) -> None:
    """Write ``model`` as a SOG folder: ``path`` (the meta.json) and its images beside it, each
    file atomically, the meta.json last; the splats in the order :mod:`.sog_order` sets."""
    from .atomic import atomic_write

    fields = fields_of(model, path, "SOG (meta.json)")
    note_lossy(path, "SOG", LOSSES, model)
    fields, kept = _in_order(fields, _kept(model, fields))
    members = encode(fields, **kept)
    _check_readable(path, fields.count, members)
    for name in [m for m in members if m != "meta.json"] + ["meta.json"]:
        with atomic_write(path if name == "meta.json" else path.parent / name) as stream:
            stream.write(members[name])


def _check_readable(path: Path, count: int, members: dict[str, bytes]) -> None:
    """Refuse a scene whose images compress beyond what the reader accepts (near-identical
    splats: :data:`PIXEL_BYTES` x count more than PLAUSIBLE_RATIO x the stored bytes + slack):
    what we write, we read back."""
    stored = sum(len(raw) for raw in members.values())
    if count * PIXEL_BYTES > PLAUSIBLE_RATIO * stored + PLAUSIBLE_SLACK:
        raise FormatError(f"{path}: {count:,} splats compress to {stored:,} bytes of images, "
                          f"more than the {PLAUSIBLE_RATIO}x a SOG reader here accepts (a scene "
                          "of near-identical splats); write .ply instead")


def _kept(model: PointModel, fields: SplatFields) -> dict:
    """encode()'s keep/same for a model read from a SOG (untouched splats keep their codes)."""
    from .splats import unchanged_rows

    codes = getattr(model.source, "quantised", None)
    if not isinstance(codes, SogCodes) or codes.means.shape[0] != fields.count:
        return {}
    same = unchanged_rows(model, fields)
    return {} if same is None else {"keep": codes, "same": same}


def _in_order(fields: SplatFields, kept: dict) -> tuple[SplatFields, dict]:
    """``fields`` and encode()'s keep/same in the order the splats are stored
    (:mod:`.sog_order`): Morton order unless ``keep`` is in force or every splat still holds
    the codes of the SOG it was read from (a re-save of an unchanged scene keeps its file's
    order; decoded positions can fall on the other side of a Morton cell's edge)."""
    from dataclasses import replace

    from .sog_order import current, morton_order, take

    if current() == "keep" or (kept and kept["same"].all()):
        return fields, kept
    perm = morton_order(fields.positions)
    if np.array_equal(perm, np.arange(fields.count)):
        return fields, kept
    fields = take(fields, perm)
    if kept:
        codes = kept["keep"]
        kept = {"keep": replace(codes, means=codes.means[perm], quats=codes.quats[perm],
                                scales=codes.scales[perm], sh0=codes.sh0[perm],
                                labels=None if codes.labels is None else codes.labels[perm]),
                "same": kept["same"][perm]}
    return fields, kept
