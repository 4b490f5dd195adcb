"""An SPZ v4 blob inside glTF's SPZ compression extension (issue 34 item 1) reads like the v3
blob of the same splats: the same quantised values (v4 keeps v3's attribute encodings)."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from splat_oracle import write_scene

from data_tools import gltf_spz
from splatdeform.errors import FormatError, InputError
from splatdeform.io import gltf, load, spz


@pytest.mark.parametrize("degree", [0, 3])
def test_v4_blob_in_glb_reads_like_the_v3_blob(tmp_path, degree):
    model = load(write_scene(tmp_path / "scene.ply", 400, degree, seed=degree + 70))
    v3 = load(gltf_spz.write(model, tmp_path / "v3.glb", version=3))
    packed = gltf_spz.write(model, tmp_path / "v4.glb", version=4)
    doc, buffers = gltf.read_document(packed)
    blob = buffers[0][:doc["bufferViews"][0]["byteLength"]]
    assert spz.is_v4(blob)   # the blob really is version 4, not gzip
    v4 = load(packed)
    assert v4.n_points == v3.n_points == 400
    np.testing.assert_array_equal(v4.positions, v3.positions)
    a, b = v4.gaussians, v3.gaussians
    for name in ("scale_log", "opacity", "sh_dc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    if degree:
        np.testing.assert_array_equal(a.sh_rest, b.sh_rest)
    # rotations: v4 keeps v3's smallest-three encoding, equal up to sign
    dots = np.abs((a.rotation * b.rotation).sum(axis=1))
    assert np.allclose(dots, np.linalg.norm(a.rotation, axis=1) * np.linalg.norm(b.rotation,
                                                                                axis=1))


def test_v4_blob_declaring_more_splats_than_the_accessors_is_refused(tmp_path):
    model = load(write_scene(tmp_path / "scene.ply", 50, 0, seed=3))
    packed = gltf_spz.write(model, tmp_path / "v4.glb", version=4)
    raw = bytearray(packed.read_bytes())
    # accessors declare 50 splats; make them declare 60: the v4 header's count disagrees
    length = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20:20 + length])
    for acc in doc["accessors"]:
        acc["count"] = 60
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (length - len(text))
    assert len(text) == length
    raw[20:20 + length] = text
    bad = tmp_path / "bad.glb"
    bad.write_bytes(bytes(raw))
    with pytest.raises((FormatError, InputError)) as info:
        load(bad)
    assert str(bad) in str(info.value) and "\n" not in str(info.value)
