"""Hostile splat files, round three (issue #32, items 2 and 4): SOG members that are not regular
files inside the model's folder, decompression bombs (a ZIP member or a gzip stream that inflates
far past what the file can need), images whose declared dimensions do not fit the splat count,
and headers that declare more splats than the file can hold.

Every case runs the real CLI in a subprocess (``info``, and ``render``/``deform`` where the path
differs) with a timeout, and checks exit 2, one error line, no traceback, and the child's peak
RSS (its VmHWM, written by a small wrapper) against 10x the file size + 300 MB. The bombs are
built in tmp_path from seeded data, as streams of repeated self-contained deflate segments (so a
1.5 GB member takes milliseconds to build, not a 1.5 GB compression).
"""

from __future__ import annotations

import gzip
import io
import json
import os
import struct
import warnings
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers import one_error_line, run_cli_peak
from splat_oracle import write_scene

import splatdeform as sd
from splatdeform.errors import FormatError, InputError
from splatdeform.io import inflate, spz
from splatdeform.io.splats import LossyWriteWarning

TIMEOUT = 60
MB = 1 << 20
# an 8000 x 8000 lossless WebP of one colour (Pillow 11 / libwebp, method 0): 40 bytes
WEBP_8000 = bytes.fromhex("5249464620000000574542505650384c140000002f3fdfcf07075081540820000a"
                          "9afec78888fe07")


def refused(path: Path, *, cwd: Path, needles=(), commands=("info",),
            file_size: int | None = None) -> None:
    """Each command on ``path``: exit 2, one line naming the file, peak RSS within bounds."""
    size = path.stat().st_size if file_size is None and path.is_file() else (file_size or 0)
    for command in commands:
        args = [command, path] if command != "render" else [command, path, "-o",
                                                            cwd / "out.png"]
        if command == "deform":
            config = cwd / "edit.yaml"
            config.write_text(yaml.safe_dump({
                "input": str(path), "output": str(cwd / "out.ply"),
                "regions": {"units": "relative",
                            "fixed": [{"box": {"min": [0, 0, 0], "max": [0.25, 1, 1]}}],
                            "handle": [{"box": {"min": [0.75, 0, 0], "max": [1, 1, 1]}}]},
                "handle": {"transform": {"translate": [0, 0.1, 0]}}}))
            args = [command, config]
        res, peak = run_cli_peak(*args, cwd=cwd)
        line = one_error_line(res, needles=needles)
        assert path.name in line, line
        assert peak <= 10 * size + 300 * MB, (command, peak / MB, size)
    assert not (cwd / "out.png").exists() and not (cwd / "out.ply").exists()


# --------------------------------------------------------------------------------------------
# fixtures: a small valid SOG (bundle and folder) and SPZ written by the project's own writers


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("round3")
    model = sd.load(write_scene(root / "scene.ply", 200, 1, seed=32))
    folder = root / "folder"
    folder.mkdir()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LossyWriteWarning)
        sd.save(model, root / "good.sog")
        sd.save(model, folder / "meta.json")
        with spz.writing_version(3):  # the gzip layout these bounds are about (v4: test_spz_v4)
            sd.save(model, root / "good.spz")
    return {"root": root, "sog": root / "good.sog", "folder": folder, "spz": root / "good.spz"}


def _members(sog: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(sog) as z:
        return {name: z.read(name) for name in z.namelist()}


def _copy_folder(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for member in src.iterdir():
        (dst / member.name).write_bytes(member.read_bytes())
    return dst


def _deflate_segment(data: bytes) -> bytes:
    """``data`` as self-contained, byte-aligned, non-final raw deflate blocks (a full flush):
    segments concatenate into one stream."""
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    return c.compress(data) + c.flush(zlib.Z_FULL_FLUSH)


FINAL = b"\x03\x00"  # an empty final (fixed Huffman) block: the end of a raw deflate stream


def _bomb(prefix: bytes, fill: int, copies: int, chunk: int = 16 * MB) -> tuple[bytes, int,
                                                                               int]:
    """(raw deflate stream, crc32, size) of ``prefix`` followed by ``copies`` x ``chunk`` bytes
    of ``fill``: a stream of about ``copies`` x 16 KB inflating to ``copies`` x ``chunk``."""
    block = bytes([fill]) * chunk
    seg = _deflate_segment(block)
    crc = zlib.crc32(prefix)
    for _ in range(copies):
        crc = zlib.crc32(block, crc)
    return (_deflate_segment(prefix) + seg * copies + FINAL, crc,
            len(prefix) + copies * chunk)


def _zip(entries: list[tuple[str, bytes, int, int, int]]) -> bytes:
    """A ZIP archive written by hand: (name, stored or deflated data, method, crc32, declared
    uncompressed size) per member, so a test can declare any size."""
    out, central = bytearray(), bytearray()
    for name, data, method, crc, size in entries:
        offset, raw = len(out), name.encode()
        out += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0x21, crc,
                           len(data), size, len(raw), 0) + raw + data
        central += struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, method, 0, 0x21,
                               crc, len(data), size, len(raw), 0, 0, 0, 0, 0, offset) + raw
    at = len(out)
    out += central + struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(entries), len(entries),
                                 len(central), at, 0)
    return bytes(out)


def _stored(members: dict[str, bytes], **replace) -> bytes:
    """The members as a stored ZIP, with ``replace``d entries (name -> entry tuple)."""
    entries = []
    for name, data in members.items():
        key = name.replace(".", "_")
        entries.append(replace.get(key, (name, data, 0, zlib.crc32(data), len(data))))
    return _zip(entries)


# --------------------------------------------------------------------------------------------
# SOG folder members: regular files inside the folder, opened through the one opener


def test_sog_folder_member_linked_to_dev_zero_is_refused_unread(good, tmp_path):
    folder = _copy_folder(good["folder"], tmp_path / "zero")
    (folder / "means_l.webp").unlink()
    (folder / "means_l.webp").symlink_to("/dev/zero")
    refused(folder / "meta.json", cwd=tmp_path, needles=("means_l.webp", "out of its folder"),
            commands=("info", "deform"))


def test_sog_folder_member_fifo_is_refused_without_hanging(good, tmp_path):
    folder = _copy_folder(good["folder"], tmp_path / "fifo")
    (folder / "quats.webp").unlink()
    os.mkfifo(folder / "quats.webp")
    refused(folder / "meta.json", cwd=tmp_path, needles=("quats.webp", "FIFO"),
            commands=("info", "deform", "render"))


def test_sog_folder_member_linked_outside_is_refused(good, tmp_path):
    folder = _copy_folder(good["folder"], tmp_path / "outside")
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    (outside / "sh0.webp").write_bytes((folder / "sh0.webp").read_bytes())  # a valid image
    (folder / "sh0.webp").unlink()
    (folder / "sh0.webp").symlink_to(outside / "sh0.webp")
    refused(folder / "meta.json", cwd=tmp_path, needles=("sh0.webp", "out of its folder"))
    # the folder given as the model: the same refusal
    res, _ = run_cli_peak("info", folder, cwd=tmp_path)
    one_error_line(res, needles=("out of its folder",))


def test_sog_folder_link_inside_the_folder_still_reads(good, tmp_path):
    """A member that links to another file of the same folder is fine (only links leaving it
    are refused)."""
    folder = _copy_folder(good["folder"], tmp_path / "inside")
    (folder / "scales.bin").write_bytes((folder / "scales.webp").read_bytes())
    (folder / "scales.webp").unlink()
    (folder / "scales.webp").symlink_to("scales.bin")
    assert sd.load(folder).n_points == 200


def test_sog_folder_oversized_meta_is_refused_unread(good, tmp_path):
    folder = _copy_folder(good["folder"], tmp_path / "bigmeta")
    meta = (folder / "meta.json").read_bytes()
    with open(folder / "meta.json", "wb") as fh:
        fh.write(meta)
        fh.truncate(64 * MB)  # sparse: 64 MB of NUL after the JSON
    refused(folder / "meta.json", cwd=tmp_path, needles=("meta.json", "more than"),
            file_size=0)


# --------------------------------------------------------------------------------------------
# SOG bundles: declared member sizes checked before inflating, inflation bounded


def test_sog_meta_json_bomb_is_refused_before_inflating(good, tmp_path):
    """A 1.5 MB .sog whose meta.json inflates (honestly declared) to 1.5 GB of JSON."""
    members = _members(good["sog"])
    stream, crc, size = _bomb(members["meta.json"], ord(" "), 96)
    path = tmp_path / "metabomb.sog"
    path.write_bytes(_stored(members, meta_json=("meta.json", stream, 8, crc, size)))
    assert path.stat().st_size < 2 * MB and size > 1500 * MB
    refused(path, cwd=tmp_path, needles=("meta.json", "declares 1,610,", "more than"),
            commands=("info", "render"))


def test_sog_member_inflating_past_its_declared_size_is_refused(good, tmp_path):
    """The same bomb declaring the meta.json's true small size: inflation stops at the
    declared size (the CRC then fails)."""
    members = _members(good["sog"])
    stream, _, _ = _bomb(members["meta.json"], ord(" "), 96)
    meta = members["meta.json"]
    path = tmp_path / "liar.sog"
    path.write_bytes(_stored(members, meta_json=("meta.json", stream, 8, zlib.crc32(meta),
                                                 len(meta))))
    refused(path, cwd=tmp_path, needles=("meta.json",))


def test_sog_gigabyte_member_is_refused_before_inflating(good, tmp_path):
    members = _members(good["sog"])
    stream, crc, size = _bomb(b"", 0, 64)
    path = tmp_path / "gigamember.sog"
    path.write_bytes(_stored(members, means_l_webp=("means_l.webp", stream, 8, crc, size)))
    assert size == 1 << 30
    refused(path, cwd=tmp_path, needles=("means_l.webp", "declares 1,073,741,824 bytes"),
            commands=("info", "render"))


def test_sog_member_declaring_more_than_deflate_can_expand_is_refused(good, tmp_path):
    members = _members(good["sog"])
    webp = members["scales.webp"]
    path = tmp_path / "ratio.sog"
    packed = _deflate_segment(webp) + FINAL
    path.write_bytes(_stored(members, scales_webp=("scales.webp", packed, 8, zlib.crc32(webp),
                                                   len(webp) * 5000)))
    with pytest.raises(FormatError, match="ratio.sog: .*scales.webp"):
        sd.load(path)


def test_sog_8000_square_webp_is_refused_from_its_header(good, tmp_path):
    """An 8000 x 8000 lossless WebP (40 bytes) in place of a 200-splat image: refused from its
    declared dimensions, never decoded (a decode takes 256 MB)."""
    from PIL import Image

    assert Image.open(io.BytesIO(WEBP_8000)).size == (8000, 8000)
    members = _members(good["sog"])
    for name in ("sh0.webp", "shN_centroids.webp"):
        changed = dict(members, **{name: WEBP_8000})
        path = tmp_path / f"huge_{name.split('.')[0]}.sog"
        path.write_bytes(_stored(changed))
        refused(path, cwd=tmp_path, needles=(name, "8000x8000"), commands=("info", "render"))


def test_sog_image_layout_rule():
    """Per-splat images: at least the count, padded by at most 4 rows, as the
    reference writer (width ceil(sqrt(n) / 4) * 4, height rounded up to 4) and ours lay them
    out."""
    from splatdeform.io.sog import _size, splat_image_fits

    for n in (1, 2, 3, 15, 16, 17, 200, 1000, 4097, 90_854, 1_000_003):
        ref_w = -(-int(np.ceil(np.sqrt(n))) // 4) * 4
        ref_h = int(np.ceil(n / ref_w / 4)) * 4
        assert splat_image_fits(ref_w, ref_h, n), (n, ref_w, ref_h)
        assert splat_image_fits(*_size(n), n), n
        assert splat_image_fits(1, n, n) and splat_image_fits(n, 1, n)
        assert not splat_image_fits(ref_w, ref_h + 8, n)
        assert not splat_image_fits(8000, 8000, n)
    assert not splat_image_fits(4, 4, 17)


# --------------------------------------------------------------------------------------------
# SPZ: gzip inflated with a maximum output of what the header declares


def _spz_bomb(count: int, fill_chunks: int, isize: int | None = None) -> bytes:
    """A gzip'd SPZ v3 (SH degree 0) header declaring ``count`` splats, followed by
    ``fill_chunks`` x 16 MB of zeros; ``isize``: the trailer's size field (default the
    true one)."""
    head = spz.HEADER.pack(spz.MAGIC, 3, count, 0, 12, 0, 0)
    stream, crc, size = _bomb(head, 0, fill_chunks)
    trailer = struct.pack("<II", crc, (size if isize is None else isize) & 0xFFFFFFFF)
    return b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x02\xff" + stream + trailer


def test_spz_gzip_bomb_is_refused_with_bounded_memory(tmp_path):
    """A 1 MB .spz declaring 4M splats (80 MB: within the 64x + 16 MiB a splat file may
    declare) whose stream inflates to 1 GB: refused before the stream passes the declared size
    (a counting pass, one chunk of memory). More splats are refused from the file size."""
    path = tmp_path / "bomb.spz"
    path.write_bytes(_spz_bomb(4_000_000, 64))
    assert path.stat().st_size < 1.2 * MB
    refused(path, cwd=tmp_path, needles=("longer than the 4,000,000 splats",),
            commands=("info", "render"))


def test_spz_gzip_bomb_with_a_forged_trailer_stops_at_the_declared_size(tmp_path):
    """The trailer claims the declared size: one pass, into a buffer of the declared size,
    refused at its first byte past it (peak: the declared 80 MB + the interpreter)."""
    count = 4_000_000
    path = tmp_path / "forged.spz"
    path.write_bytes(_spz_bomb(count, 64, isize=spz.HEADER.size + spz.body_size(count, 0, 3)))
    refused(path, cwd=tmp_path, needles=("longer than the 4,000,000 splats",))
    path.write_bytes(_spz_bomb(10_000_000, 64))   # 200 MB from 1 MB: not even inflated
    refused(path, cwd=tmp_path, needles=("10,000,000 splats", "compresses at most 64x"))


def test_spz_declaring_2e8_splats_is_refused_from_the_file_size(tmp_path):
    head = spz.HEADER.pack(spz.MAGIC, 3, 200_000_000, 0, 12, 0, 0)
    path = tmp_path / "huge.spz"
    path.write_bytes(gzip.compress(head + bytes(np.random.default_rng(32).integers(
        0, 256, 100_000, dtype=np.uint8)), mtime=0))
    refused(path, cwd=tmp_path, needles=("200,000,000 splats", "compressed bytes can hold"),
            commands=("info", "render"))


def test_spz_blob_decoder_is_bounded_in_process(good):
    """The public bytes decoder (what the glTF SPZ extension uses) has the same bounds."""
    blob = good["spz"].read_bytes()
    fields, info = spz.decode_blob("x.glb", blob)
    assert fields.count == info["count"] == 200
    with pytest.raises(FormatError, match="x.glb: .*longer than the 1,500,000 splats"):
        spz.gunzip_blob("x.glb", _spz_bomb(1_500_000, 16))
    with pytest.raises(FormatError, match="x.glb: .*10,000,000 splats.*compresses at most"):
        spz.gunzip_blob("x.glb", _spz_bomb(10_000_000, 16))
    with pytest.raises(FormatError, match="x.glb: .*compressed bytes can hold"):
        spz.gunzip_blob("x.glb", gzip.compress(spz.HEADER.pack(spz.MAGIC, 3, 2 * 10**8, 3, 12,
                                                                0, 0)))
    with pytest.raises(FormatError, match="x.glb: .*shorter than the 200 splats"):
        spz.gunzip_blob("x.glb", gzip.compress(gzip.decompress(blob)[:-7]))
    with pytest.raises(FormatError, match="x.glb: .*more than this reader's limit"):
        spz.gunzip_blob("x.glb", blob, limit=100)


def test_spz_multi_member_and_padded_gzip_still_read(good, tmp_path):
    """Python's gzip reads several members and zero padding: so does the bounded reader."""
    raw = gzip.decompress(good["spz"].read_bytes())
    path = tmp_path / "members.spz"
    path.write_bytes(gzip.compress(raw[:1000]) + gzip.compress(raw[1000:]) + b"\0" * 8)
    assert sd.load(path).n_points == 200
    path.write_bytes(gzip.compress(raw) + b"junk")
    with pytest.raises(FormatError, match="members.spz: .*after the end of its gzip stream"):
        sd.load(path)


# --------------------------------------------------------------------------------------------
# compressed PLY and .splat: declared counts against the file size, the one opener


def test_compressed_ply_counts_are_checked_against_the_file_size(good, tmp_path):
    from data_tools.playcanvas import compressed_ply

    rng = np.random.default_rng(32)
    n = 300
    raw = compressed_ply(rng.normal(size=(n, 3)), rng.normal(-4, 1, size=(n, 3)),
                         rng.normal(size=(n, 4)), rng.normal(size=n), rng.normal(size=(n, 3)),
                         rng.normal(size=(n, 9)))
    assert b"element vertex 300" in raw
    for old, new in ((b"element vertex 300", b"element vertex 1000000000"),
                     (b"element chunk 2", b"element chunk 400000000"),
                     (b"element sh 300", b"element sh 3000000000")):
        path = tmp_path / "lying.compressed.ply"
        path.write_bytes(raw.replace(old, new, 1))
        refused(path, cwd=tmp_path, needles=("lying.compressed.ply",))


def test_splat_file_linked_to_dev_zero_or_a_fifo_is_refused(tmp_path):
    zero = tmp_path / "zero.splat"
    zero.symlink_to("/dev/zero")
    refused(zero, cwd=tmp_path, needles=("character device",), file_size=0,
            commands=("info", "render"))
    fifo = tmp_path / "pipe.splat"
    os.mkfifo(fifo)
    refused(fifo, cwd=tmp_path, needles=("FIFO",), file_size=0, commands=("info", "render"))
    with pytest.raises(InputError, match="pipe.splat: is a named pipe"):
        from splatdeform.io.splats import read_bytes

        read_bytes(fifo)


# --------------------------------------------------------------------------------------------
# the inflate helpers


def test_inflate_gzip_bounds():
    data = bytes(np.random.default_rng(32).integers(0, 256, 5000, dtype=np.uint8))
    packed = gzip.compress(data)
    assert inflate.inflate_gzip(packed, 5000, "blob", "x.bin", exact=True) == data
    with pytest.raises(FormatError, match="x.bin: blob is longer than the 4,999 bytes"):
        inflate.inflate_gzip(packed, 4999, "blob", "x.bin")
    with pytest.raises(FormatError, match="x.bin: blob ends after 5,000 bytes, short of"):
        inflate.inflate_gzip(packed, 5001, "blob", "x.bin", exact=True)
    with pytest.raises(FormatError, match="x.bin: blob ends inside its compressed stream"):
        inflate.inflate_gzip(packed[:-20], 5000, "blob", "x.bin")
    with pytest.raises(FormatError, match="x.bin: blob is not a valid gzip stream"):
        inflate.inflate_gzip(b"not gzip at all", 5000, "blob", "x.bin")
    with pytest.raises(FormatError, match="x.bin: blob is empty"):
        inflate.inflate_gzip(b"", 5000, "blob", "x.bin")
    # a file source reads the same
    assert inflate.inflate_gzip(io.BytesIO(packed), 5000, "blob", "x.bin") == data


def test_inflate_zip_member_bounds(tmp_path):
    data = json.dumps({"a": list(range(1000))}).encode()
    path = tmp_path / "a.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("m.json", data)
        z.writestr("s.bin", data, compress_type=zipfile.ZIP_STORED)
        z.writestr("b.bin", data, compress_type=zipfile.ZIP_BZIP2)
    with zipfile.ZipFile(path) as z:
        assert inflate.inflate_zip_member(z, z.getinfo("m.json"), 10**6, "member", path) == data
        assert inflate.inflate_zip_member(z, z.getinfo("s.bin"), 10**6, "member", path) == data
        with pytest.raises(FormatError, match="a.zip: member m.json declares .* more than"):
            inflate.inflate_zip_member(z, z.getinfo("m.json"), 100, "member", path)
        with pytest.raises(FormatError, match="compression method 12"):
            inflate.inflate_zip_member(z, z.getinfo("b.bin"), 10**6, "member", path)


def test_real_splats_still_read_under_the_bounds(tmp_path):
    """The real captures (90,854 splats SH0; 6,831 splats SH3) written as SOG and SPZ read back
    whole: the bounds (image layout, member sizes, declared stream sizes) pass real files."""
    from conftest import shared_file

    for rel in ("splats/guitar_3dgs_sh0.ply", "splats/tile_3dgs_sh3.ply"):
        model = sd.load(shared_file(rel))
        for ext in (".sog", ".spz"):
            out = tmp_path / f"real{ext}"
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", LossyWriteWarning)
                sd.save(model, out)
            back = sd.load(out)
            assert back.n_points == model.n_points, (rel, ext)
            assert np.isfinite(back.positions).all()
