"""PLY (every variant but PlayCanvas's compressed one, :mod:`.splats`): the reader's own header
parser (:func:`splatdeform.io.ply_format.parse_header`), validated against the file size, is the
probe.

A header can lie and a body can amplify: ASCII values and PLY list rows cost several times
their bytes once parsed, so the load estimate takes the larger of what the header's counts
imply and what the file's size can hold.
"""

from __future__ import annotations

from pathlib import Path

from ..format import FileCost, Format

# Measured parse costs of the PLY reader (tests/test_memory.py checks them as upper bounds):
ASCII_BYTES_PER_TOKEN = 64    # a bytes object and its list slot from split(), the float64 value
ASCII_BYTES_PER_LINE = 64     # a bytes object per body line and its slot in two lists
LIST_BYTES_PER_ROW = 400     # one numpy array object per non-empty list row (np.split views,
                              # the object column), row offsets and lengths (measured ~350)
LIST_BYTES_PER_VALUE = 8      # a gather index (int64) per list value
LIST_BYTES_PER_ITEM_BYTE = 10  # per byte of a list value: its byte indices (int64) and copies
COPIES_OF_FILE = 3            # binary: the raw bytes, a copied body, the decoded columns
ASCII_COPIES_OF_FILE = 5      # ascii: raw bytes, split lines, joined rows, tokens, values


def header(path: Path, head: bytes, size: int):
    """The PLY header of ``head``, its declared rows checked to fit the body (one FormatError
    line otherwise). Returns (header, body bytes)."""
    from ..ply_format import parse_header

    parsed = parse_header(path, head)
    body = max(size - parsed.size, 0)
    check_counts(path, parsed, body)
    return parsed, body


def probe(path: Path, head: bytes, size: int, file: Path | None = None) -> FileCost:
    """The PLY reader's peak from the header's counts and the file's size: binary rows are
    copied once, but every non-empty list row becomes an array object and an ASCII token a
    Python bytes object (tens of bytes for a two-byte token), so a list- or token-dense body
    costs up to ~30x its size. Counts are bounded by what the size can hold, so a lying
    header cannot make the estimate small."""
    import numpy as np

    parsed, body = header(path, head, size)
    points = sum(count for el, count, _ in parsed.elements if el == "vertex")
    record = 0
    for el, _, props in parsed.elements:
        if el == "vertex":
            record = sum(np.dtype(p.dtype).itemsize for p in props if not p.is_list)
    record = max(record, 12) + 48   # float64 positions and normals beside the stored columns
    load = (ASCII_COPIES_OF_FILE if parsed.text else COPIES_OF_FILE) * size
    if parsed.text:
        tokens = min(body // 2 + 1, sum(count * len(props) for _, count, props in
                                        parsed.elements
                                        if not any(p.is_list for p in props)))
        if any(p.is_list for _, _, props in parsed.elements for p in props):
            tokens = body // 2 + 1   # list values: as many tokens as the body can hold
        lines = min(body // 2 + 1, sum(count for _, count, _ in parsed.elements))
        load += tokens * ASCII_BYTES_PER_TOKEN + lines * ASCII_BYTES_PER_LINE
    else:
        for _, count, props in parsed.elements:
            lists = [p for p in props if p.is_list]
            if not lists:
                continue
            smallest = min(np.dtype(p.dtype).itemsize for p in lists)
            values = body // smallest
            rows = min(count, body // max(1, sum(np.dtype(p.len_dtype).itemsize
                                                 for p in lists)))
            load += rows * (LIST_BYTES_PER_ROW * len(lists) + 16 * len(props)) + \
                values * (LIST_BYTES_PER_VALUE + LIST_BYTES_PER_ITEM_BYTE * smallest)
    return FileCost(points, size, record, max(load, 2 * size + points * record))


def check_counts(path: Path, header, body: int) -> None:
    """The PLY reader's own size check (:func:`..ply_format.check_declared_size`) on the header
    it parsed: the declared rows must fit in the body, else one FormatError line."""
    from ..ply_format import check_declared_size

    check_declared_size(path, header, body)


FORMATS = {".ply": Format("ply", "ply", chunk_class="PlyChunks", probe=probe)}
