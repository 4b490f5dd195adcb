"""Reading a YAML config (edit or batch) safely: a size cap before parsing, integers too long
to be a config number kept as :class:`~splatdeform.edit.schema.LongInt` (refused by the key
that holds it), the parsed values counted with aliases expanded before anything validates them.
Every error is one :class:`ConfigError` line naming the file."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from splatdeform.edit.schema import MAX_INT_DIGITS, LongInt
from splatdeform.errors import ConfigError
from splatdeform.io.regular import open_regular

MAX_CONFIG_BYTES = 2 * 2**20  # a config file (edit or batch); larger data goes in files
MAX_CONFIG_NODES = 1_000_000  # values in the parsed config, aliases counted where they expand
#: YAML events (scalars, collection starts and ends, aliases) counted by streaming the parser
#: before anything is built: the composed nodes cost ~0.5 KB each (800,000 events of inline
#: pairs in a 1.4 MB file reached 390 MB); 200,000 keep a config under ~100 MB.
MAX_CONFIG_EVENTS = 200_000
_SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml: the same YAML, 10x faster


class _Loader(_SafeLoader):  # type: ignore[misc,valid-type]
    """The safe loader, with integers too long to be a config number kept as :class:`LongInt`
    (refused by the key that holds it) instead of converted (Python raises ValueError past
    4,300 digits)."""


#: numbers are read strictly, as the PLY reader and the pairs files read them: YAML 1.1 also
#: reads ``1_0.5`` as 10.5, ``0x10`` as 16, ``0o17`` as 15 and ``1:30`` as 90; such a value
#: stays the text it is, and the key that holds it refuses it ("expected a number, got '1_0.5'")
_PLAIN_INT = re.compile(r"[-+]?[0-9]+")
_PLAIN_FLOAT = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?"
                          r"|[-+]?\.(inf|Inf|INF)|\.(nan|NaN|NAN)")


def _construct_int(loader: Any, node: yaml.ScalarNode) -> int | LongInt | str:
    text = str(node.value)
    if not _PLAIN_INT.fullmatch(text):
        return text
    digits = len(text.lstrip("+-"))
    if digits > MAX_INT_DIGITS:
        return LongInt(digits)
    return yaml.SafeLoader.construct_yaml_int(loader, node)


def _construct_float(loader: Any, node: yaml.ScalarNode) -> float | str:
    text = str(node.value)
    if not _PLAIN_FLOAT.fullmatch(text):
        return text
    return yaml.SafeLoader.construct_yaml_float(loader, node)


_Loader.add_constructor("tag:yaml.org,2002:int", _construct_int)
_Loader.add_constructor("tag:yaml.org,2002:float", _construct_float)


def _expanded_size(data: Any, limit: int) -> int:
    """How many values ``data`` holds with every alias expanded (a shared list counts once per
    use); stops counting past ``limit``. Linear in the distinct nodes (memoised by id)."""
    memo: dict[int, int] = {}

    def size(obj: Any) -> int:
        if not isinstance(obj, dict | list):
            return 1
        key = id(obj)
        if key in memo:
            return memo[key]
        memo[key] = limit + 1  # a node reached again while it is counted: a cycle
        children = obj.items() if isinstance(obj, dict) else ((None, v) for v in obj)
        total = 1
        for k, v in children:
            total += size(k) + size(v) if k is not None else size(v)
            if total > limit:
                break
        memo[key] = min(total, limit + 1)
        return memo[key]

    return size(data)


def _read_text(path: Path) -> str:
    with open_regular(path, what="config file") as f:   # the one opener: never a FIFO
        raw = f.read(MAX_CONFIG_BYTES + 1)
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: the config is larger than {MAX_CONFIG_BYTES >> 20} MB; keep "
                          "long data in files (e.g. indices: {file: picked.txt})")
    nul = raw.find(b"\0")
    if nul >= 0:
        raise ConfigError(f"{path}: contains a NUL byte at offset {nul}; expected a YAML text "
                          "file")
    return raw.decode("utf-8")


def _count_events(path: Path, text: str) -> None:
    """Stream the parser's events (constant memory) and refuse past :data:`MAX_CONFIG_EVENTS`
    before any node is built."""
    for count, _ in enumerate(yaml.parse(text, Loader=_SafeLoader)):
        if count >= MAX_CONFIG_EVENTS:
            raise ConfigError(f"{path}: the config holds more than {MAX_CONFIG_EVENTS:,} YAML "
                              "values; keep long data in files (e.g. indices: {file: "
                              "picked.txt}, points.pairs: {file: gcp.csv})")


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Parse a YAML mapping; ConfigError naming the file for missing/invalid files. The file is
    read with a size cap (:data:`MAX_CONFIG_BYTES`) and the parsed values are counted with
    aliases expanded (:data:`MAX_CONFIG_NODES`) before anything validates them."""
    path = Path(path)
    if "\x00" in str(path):
        raise ConfigError(f"{str(path)!r}: a path must not contain a NUL byte")
    if not path.is_file():
        what = "is not a regular file" if path.exists() else "config file not found"
        raise ConfigError(f"{path}: {what}")
    try:
        text = _read_text(path)
        _count_events(path, text)
        data = yaml.load(text, Loader=_Loader)  # noqa: S506 (a safe loader)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    except RecursionError:
        raise ConfigError(f"{path}: invalid YAML: nested too deeply") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
        if "nesting depth" in problem:  # libyaml's words for what PyYAML hits as recursion
            problem = "nested too deeply"
        raise ConfigError(f"{path}:{where} invalid YAML: {problem}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a text file") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a YAML mapping of config keys at the top level")
    try:
        n = _expanded_size(data, MAX_CONFIG_NODES)
    except RecursionError:
        raise ConfigError(f"{path}: invalid YAML: nested too deeply") from None
    if n > MAX_CONFIG_NODES:
        raise ConfigError(f"{path}: the config holds more than {MAX_CONFIG_NODES:,} values "
                          "(counting where aliases repeat them); keep long data in files "
                          "(e.g. indices: {file: picked.txt})")
    return data
