"""The 3D Gaussian splat formats: PlayCanvas's compressed PLY, ``.splat``, ``.ksplat`` (read
only), SPZ, SOG (a bundle or a folder's ``meta.json``) and glTF ``KHR_gaussian_splatting``
(``.glb``/``.gltf``).

Each probe reads only a header, through the one opener, with the reader's own checks, and counts
the splats that header declares (SPZ: the gzip stream's 16-byte header; SOG: meta.json's count;
glTF: the POSITION accessors' counts; compressed PLY: the vertex element's count; ``.splat``:
the size over its 32-byte record; ``.ksplat``: its main header's count), so a small file that
declares many splats gets an estimate from what it declares and an explicit memory budget caps it.
"""

from __future__ import annotations

from pathlib import Path

from ..format import FileCost, Format, size_cost
from . import ply

#: float32 values of a decoded splat besides its SH rest: position 3, scale 3, rotation 4,
#: opacity 1, SH DC 3
SPLAT_FLOATS = 14
#: the model's float64 positions (and normals) beside the decoded table
MODEL_BYTES = 48
SH_REST = {0: 0, 1: 9, 2: 24, 3: 45, 4: 72}


def splat_record(n_rest: int) -> int:
    """Bytes a decoded splat takes in the model: its float32 table row (``n_rest`` SH rest
    values) and float64 positions."""
    return 4 * (SPLAT_FLOATS + n_rest) + MODEL_BYTES


def _cost(points: int, size: int, n_rest: int, decoded: int) -> FileCost:
    """``points`` splats of ``n_rest`` SH rest values whose decode holds ``decoded`` bytes at
    its peak, then builds the model's table."""
    record = splat_record(n_rest)
    return FileCost(points, size, record, size + decoded + points * record)


def _spz_probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """The gzip stream's header (inflated from the first bytes) and the reader's checks of its
    declared size against the compressed size and the machine's memory; v4: its plaintext
    header (the count; the table is checked by the reader)."""
    from .. import spz
    from ..inflate import Inflater, check_declared

    if spz.is_v4(head):
        info = spz.parse_header(path, head[:spz.HEADER.size])
        check_declared(path, f"SPZ data (SPZ header: {info['count']:,} splats)",
                       spz.stream_size(info), decoded=spz.decoded_size(info))
        spz.check_plausible(path, info, size)
        return _cost(info["count"], size, 3 * spz.SH_COEFFS[info["sh_degree"]],
                     spz.decoded_size(info))
    spz._refuse_plain(path, head[:spz.HEADER.size])
    info = spz.parse_header(path, Inflater(head, path, "SPZ data").read(spz.HEADER.size))
    check_declared(path, f"SPZ data (SPZ header: {info['count']:,} splats)",
                   spz.stream_size(info), size, decoded=spz.decoded_size(info))
    spz.check_plausible(path, info, size)
    return _cost(info["count"], size, 3 * spz.SH_COEFFS[info["sh_degree"]],
                 spz.decoded_size(info))


def _sog_probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """meta.json's count (of a bundle: its ZIP member; the reader's checks), and the decode's
    bytes per splat and SH coefficient; an archive member (no file) by its size."""
    from .. import sog

    if file is None:
        return size_cost(size)
    info = sog.read_info(file)
    bands = info["sh_bands"]
    n, k = info["count"], sog.SH_COEFFS.get(bands, 0) if isinstance(bands, int) else 0
    return _cost(n, size, 3 * k, n * (sog.DECODED_PER_SPLAT + sog.DECODED_PER_COEFF * k))


def _gltf_probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """The POSITION accessors' counts of the splat primitives (the JSON alone)."""
    from .. import gltf

    declared = gltf.declared_splats(path, head, size, file)
    if declared is None:
        return size_cost(size)
    points, degree = declared
    n_rest = SH_REST[degree]
    return _cost(points, size, n_rest, 2 * size + 2 * points * 4 * (SPLAT_FLOATS + n_rest))


def _compressed_ply_probe(path: Path, head: bytes, size: int,
                          file: Path | None = None) -> FileCost:
    """The PLY header (the reader's parser and size check): the vertex element's count, the
    sh element's coefficients; the packed rows and their decoded table."""
    parsed, _ = ply.header(path, head, size)
    points = sum(count for el, count, _ in parsed.elements if el == "vertex")
    n_rest = sum(len(props) for el, _, props in parsed.elements if el == "sh")
    decoded = ply.COPIES_OF_FILE * size + 2 * points * 4 * (SPLAT_FLOATS + n_rest)
    return _cost(points, size, n_rest, decoded)


def _splat_probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """32-byte records, nothing else."""
    points = max(size // 32, 1)
    return FileCost(points, size, 96, 3 * size + 96 * points)


def _ksplat_probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """The main header's splat count (checked against the size by the reader's parser) and the
    SH degree of the first section header when the head holds it; the whole file is read,
    then decoded to float32."""
    from .. import ksplat

    info = ksplat.parse_main(path, head, size)
    first = ksplat.HEADER_BYTES + ksplat.SECTION_BYTES
    degree = ksplat.SECTION.unpack_from(head, ksplat.HEADER_BYTES)[-1] \
        if len(head) >= first else 3
    n_rest = SH_REST.get(degree, SH_REST[3])
    return _cost(info["count"], size, n_rest,
                 size + info["count"] * 4 * (SPLAT_FLOATS + n_rest) * 2)


def _ksplat_fields(path: Path) -> dict:
    from .. import ksplat

    h = ksplat.read_info(path)
    return {"format": f".ksplat v{h['version']} (GaussianSplats3D, read only)", "format_fields": {
        "compression_level": h["level"], "sections": h["sections"], "sh_degree": h["sh_degree"]}}


def _compressed_ply_fields(path: Path) -> dict:
    from .. import ply as ply_module

    source = ply_module.read_ply(path)
    chunk, sh = source.element("chunk"), source.element("sh")
    n_rest = 0 if sh is None else len(sh.properties)
    return {"format": "PlayCanvas compressed PLY", "format_fields": {
        "chunks": 0 if chunk is None else chunk.count, "sh_bands": {0: 0, 9: 1, 24: 2, 45: 3, 72: 4}
        .get(n_rest, n_rest)}}


def _splat_fields(path: Path) -> dict:
    return {"format": ".splat (32-byte records)"}


def _spz_fields(path: Path) -> dict:
    from .. import spz

    h = spz.read_info(path)
    packing = "ZSTD streams" if h["version"] == 4 else "gzip"
    fields = {"extensions": ", ".join(f"{kind:#010x}" for kind, _ in h["extensions"]) or
              "none"} if h["version"] == 4 else {}
    return {"format": f"SPZ v{h['version']} ({packing})", "format_fields": {**fields,
        "version": h["version"], "sh_degree": h["sh_degree"],
        "fractional_bits": h["fractional_bits"], "antialiased": h["antialiased"]}}


def _gltf_fields(path: Path) -> dict:
    from .. import gltf

    doc, _ = gltf.read_document(path)
    used = doc.get("extensionsUsed", [])
    return {"format": "glTF 2.0 " + ("binary (.glb)" if path.name.lower().endswith(".glb")
                                     else "JSON (.gltf)"),
            "format_fields": {"extensions": ", ".join(used) or "none",
                              "generator": doc.get("asset", {}).get("generator", "?")}}


def _sog_fields(path: Path) -> dict:
    from .. import sog

    h = sog.read_info(path)
    return {"format": f"PlayCanvas SOG v{h['version']} "
            + ("bundle (.sog)" if path.name.lower().endswith(".sog") else "folder (meta.json)"),
            "format_fields": {"sh_bands": h["sh_bands"], "palette": h["palette"],
                              "antialias": h["antialias"], "generator": h["generator"]}}


#: a SOG folder's file (the table's whole-name key)
SOG_META = "meta.json"
_SOG = {"probe": _sog_probe, "fields": _sog_fields, "lossy": True}
_GLTF = Format("gltf", probe=_gltf_probe, fields=_gltf_fields)

#: Formats read here but never written: extension -> the refusal (after the output's path),
#: said before any work or any file (:func:`splatdeform.io.check_writable`).
READ_ONLY = {".ksplat": ".ksplat is read only here; write .splat, .spz, .sog, .compressed.ply "
                        "or .ply (the GaussianSplats3D viewer reads them)"}

FORMATS = {
    ".compressed.ply": Format("ply", writer="playcanvas", probe=_compressed_ply_probe,
                              fields=_compressed_ply_fields, lossy=True),
    ".splat": Format("splat", probe=_splat_probe, fields=_splat_fields, lossy=True),
    ".ksplat": Format("ksplat", probe=_ksplat_probe, fields=_ksplat_fields, lossy=True),
    ".spz": Format("spz", probe=_spz_probe, fields=_spz_fields, lossy=True),
    ".sog": Format("sog", **_SOG),
    SOG_META: Format("sog", "folder", **_SOG),
    ".glb": _GLTF,
    ".gltf": _GLTF,
}

__all__ = ["FORMATS", "SOG_META", "splat_record"]
