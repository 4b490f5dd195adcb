"""``splatdeform apply FIELD.npz MODEL -o OUT``: a saved field on a model, knowing where it was
fitted.

A field is fitted on one model: its ``support`` (:attr:`splatdeform.field.Field.support`) is
the box of its constraints and of that model. Applied elsewhere it extrapolates: the points
it moves that lie outside the support are counted (:class:`~splatdeform.field.SupportStats`)
and said in one warning line naming the output (how many, and the largest distance from the
box in model units); a model whose box does not overlap the support at all is refused
(exit 2) unless ``--extrapolate`` is given (a field fitted on one LiDAR tile moved a tile
636 km away by 20 km without a word).

Warnings raised while the output is written (a LAS writer moving its offset) name the output,
never the temporary file beside it.
"""

from __future__ import annotations

import contextlib
import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from splatdeform.errors import InputError
from splatdeform.field import Field, SupportStats


def _box(lo, hi) -> str:
    return "[" + ", ".join(f"{v:.6g}" for v in lo) + "] .. [" + ", ".join(
        f"{v:.6g}" for v in hi) + "]"


def check_support(stats: SupportStats, field_obj: Field, field_path: Path, model_path: Path,
                  out: Path, extrapolate: bool) -> None:
    """Refuse a model entirely outside the field's support (unless ``extrapolate``); warn (one
    line naming ``out``) when the field moves points outside it."""
    box = field_obj.support
    note = field_obj.support_note
    if not stats.overlaps(box) and not extrapolate:
        raise InputError(f"{model_path}: lies entirely outside the support of field "
                         f"{field_path} (the model's box {_box(stats.lo, stats.hi)}, the "
                         f"field's {_box(box[0], box[1])}{note}); a field applies where it was "
                         "fitted: give --extrapolate to apply it anyway")
    if stats.outside:
        warnings.warn(f"{out}: {stats.outside:,} of the {stats.moved:,} points the field moves "
                      f"lie outside its support (the box {_box(box[0], box[1])} of its "
                      f"constraints and fitted model{note}), up to {stats.distance:.6g} model "
                      "units from it: the field extrapolates there", stacklevel=2)


def _finite(model, field_path: Path, model_path: Path):
    """``model`` when its positions are finite; else InputError: finite but huge weights or
    displacements in the field overflowed (nothing is written)."""
    if not np.isfinite(model.positions).all():
        raise InputError(f"field {field_path}: moves points of {model_path} to infinite or NaN "
                         "positions (its weights or displacements overflow); nothing written")
    return model


@contextlib.contextmanager
def _naming_field(field_path: Path, model_path: Path) -> Iterator[None]:
    """An error raised while the field is evaluated names the field (a field of finite but
    huge weights overflows in the evaluation, whose own line names no file)."""
    try:
        yield
    except InputError as exc:
        if str(field_path) in str(exc) or str(model_path) in str(exc):
            raise  # it names what it is about
        raise InputError(f"field {field_path}: on {model_path}: {exc}") from None


@contextlib.contextmanager
def naming_output(out: Path) -> Iterator[None]:
    """Warnings raised inside (e.g. by a writer) name ``out`` where they named its temporary
    file (``.NAME.<pid>-<random>.tmp.EXT``, :func:`splatdeform.io.atomic.atomic_path`); they are
    shown when the block ends (also when it raises)."""
    temp = re.compile(r"(?:[^\s'\"]*/)?\." + re.escape(out.stem) + r"\.[1-9][0-9]{0,9}-"
                      r"[a-z0-9_]{8}\.tmp" + re.escape(out.suffix))
    caught: list = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            yield
    finally:
        for w in caught:
            text = temp.sub(lambda _m: str(out), str(w.message))
            warnings.warn_explicit(text, w.category, w.filename, w.lineno)


def apply_file(field_path: str | Path, model_path: str | Path, out: str | Path, *,
               backend: str | None = None, budget: int | None = None,
               extrapolate: bool = False) -> tuple[Path, bool]:
    """``splatdeform apply``: (the output, streamed). In memory when the model's in-memory
    estimate fits the budget (:func:`splatdeform.memory.choose`),
    else streamed in chunks (binary PLY, LAS/LAZ: :func:`splatdeform.io.open_chunks`);
    ``budget`` None: half the RAM. Refused (one line) when the output is an input, when a field
    with ``indices`` selectors would stream (its indices are global), when the model lies
    entirely outside the field's support and not ``extrapolate`` (see the module)."""
    from splatdeform.io import STREAMABLE, SUPPORTED, extension_of, load, open_chunks, save
    from splatdeform.io.plan import plan_io
    from splatdeform.memory import choose, deform_peak, file_cost

    out, field_path, model_path = Path(out), Path(field_path), Path(model_path)
    plan_io([("field", field_path), ("model", model_path)], [("-o/--output", out)])
    if extension_of(out) not in SUPPORTED:
        raise InputError(f"{out}: unknown output extension {extension_of(out) or '(none)'!r}; "
                         f"expected one of {', '.join(SUPPORTED)}")
    fld = Field.load(field_path)
    cost = file_cost(model_path)
    same_format = extension_of(out) == extension_of(model_path)
    streamable = extension_of(model_path) in STREAMABLE and same_format and \
        bool(fld.meta.get("transferable", True))
    choice = choose(deform_peak(cost, max_centers=0), budget, streamable=streamable,
                    name=model_path, why_not="it cannot stream (format, output format or "
                    "indices selectors)")
    if choice.mode == "refuse":
        raise InputError(choice.message)
    stats = SupportStats()
    if choice.mode == "memory":
        model = load(model_path)
        whole = SupportStats()  # the model's box first: a model entirely outside is refused
        whole.add(model.positions, np.empty(0, dtype=np.int64), fld.support)
        check_support(whole, fld, field_path, model_path, out, extrapolate)
        with _naming_field(field_path, model_path):
            moved = _finite(fld.apply(model, backend, support=stats), field_path, model_path)
        check_support(stats, fld, field_path, model_path, out, extrapolate)
        with naming_output(out):
            save(moved, out)
        return out, False
    from splatdeform.io.chunks import map_chunks
    from splatdeform.memory import stream_chunk

    src = open_chunks(model_path)
    chunk = stream_chunk(choice.budget, src.record_bytes,
                         int(getattr(cost, "reader_bytes", 0)) + 160 * 2**20)

    from splatdeform.edit.stream.split import Spill, field_children, field_split

    with _naming_field(field_path, model_path):   # gaussians.split: decided for the file
        decision = field_split(fld, src, chunk, backend)
    spill = Spill(out) if decision is not None and decision.rows.size else None

    def part(a: int, b: int):
        model = src.read(a, b)
        moved = _finite(fld.apply(model, backend, support=stats, split="off"),  # split below
                        field_path, model_path)
        if spill is not None:   # child 0 in its parent's row, the others spilled in order
            field_children(fld, model, moved, a, b, decision, backend, lambda kids: spill.write(
                src.encode(_finite(kids, field_path, model_path))[0]))
        return src.encode(moved)

    try:
        with naming_output(out), _naming_field(field_path, model_path):
            map_chunks(src, out, part, chunk, before_rename=lambda: check_support(  # last check
                stats, fld, field_path, model_path, out, extrapolate),
                extra=0 if spill is None else decision.extra,
                appendix=None if spill is None else lambda: spill.blocks(chunk))
    finally:
        if spill is not None:
            spill.close()
    return out, True
