"""Write a ``.glb`` whose splats are SPZ-compressed (``KHR_gaussian_splatting`` with the nested
``KHR_gaussian_splatting_compression_spz`` extension), following the extension's written
specification (KhronosGroup/glTF, extensions/2.0/Khronos/KHR_gaussian_splatting_compression_spz):
the primitive keeps its attribute accessors (type and count, no bufferView), the extension's
``bufferView`` holds the gzip'd SPZ stream, packed in glTF's Left-Up-Front frame. splatdeform reads
such files; this writer makes the test files (no pinned tool writes them).

    python -m data_tools.gltf_spz scene.ply out.glb [--name NAME]  # NAME: the _spz or _spz_2 key
"""

from __future__ import annotations

import argparse
import gzip
from pathlib import Path

from splatdeform.io import gltf, load, spz
from splatdeform.io.atomic import atomic_write
from splatdeform.io.splats import SH_COEFFS, fields_of


def write(model, path: str | Path, name: str = gltf.SPZ_EXTS[0], version: int = 3) -> Path:
    """Write ``model`` (3D Gaussian splats) to ``path`` as an SPZ-compressed glb."""
    f = fields_of(model, path, ".glb")
    stream = spz.encode(f, version=version, frame=spz.LUF)
    # v2/v3: the gzip'd stream; v4: the version-4 file itself (header, table, ZSTD streams)
    blob = spz.write_v4(stream) if version == 4 else gzip.compress(stream, mtime=0)
    degree = {k: d for d, k in SH_COEFFS.items()}[f.sh_rest.shape[2]]
    luf = f.positions * spz.LUF_FLIP
    attributes = {"POSITION": ("VEC3", {"min": luf.min(axis=0).tolist(),
                                        "max": luf.max(axis=0).tolist()}),
                  "COLOR_0": ("VEC4", {}),
                  f"{gltf.EXT}:SCALE": ("VEC3", {}), f"{gltf.EXT}:ROTATION": ("VEC4", {}),
                  **{sh: ("VEC3", {}) for sh in gltf._sh_names(degree)}}
    accessors = [{"componentType": gltf.FLOAT, "count": f.count, "type": kind, **extra}
                 for kind, extra in attributes.values()]
    doc = {"asset": {"version": "2.0", "generator": "splatdeform data_tools.gltf_spz"},
           "extensionsUsed": [gltf.EXT, name], "extensionsRequired": [name],
           "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{
               "attributes": {a: i for i, a in enumerate(attributes)}, "mode": 0,
               "extensions": {gltf.EXT: {"kernel": "ellipse",
                                         "colorSpace": "srgb_rec709_display",
                                         "extensions": {name: {"bufferView": 0}}}}}]}],
           "accessors": accessors,
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(blob)}],
           "buffers": [{"byteLength": len(blob) + (-len(blob)) % 4}]}
    with atomic_write(Path(path)) as stream:
        gltf.write_glb(stream, doc, [blob, b"\0" * ((-len(blob)) % 4)])
    return Path(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source")
    parser.add_argument("output")
    parser.add_argument("--name", default=gltf.SPZ_EXTS[0], choices=gltf.SPZ_EXTS)
    args = parser.parse_args()
    write(load(args.source), args.output, args.name)


if __name__ == "__main__":
    main()
