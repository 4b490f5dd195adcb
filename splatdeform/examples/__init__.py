"""``splatdeform example NAME [DIR]``: the quick start's scans and edit configs, written from
the installed package (no clone, no download).

Each example is a generated scan (seeded: the same bytes on every machine) and an edit config
that reads it by a relative path, so ``splatdeform deform DIR/CONFIG`` runs as it is.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from splatdeform.errors import InputError

#: name -> (what it is, [(file, maker)]); a maker is "bar", "sphere", "drifted", "gcp" or a
#: config's name
EXAMPLES: dict[str, tuple[str, list[tuple[str, str]]]] = {
    "bar": ("the quick start: a bumpy bar (20,000 points) and bend.yaml, a handle edit",
            [("scans/bar.ply", "bar"), ("bend.yaml", "BEND")]),
    "curve": ("the bumpy bar and curve.yaml, a curve edit raising its middle",
              [("scans/bar.ply", "bar"), ("curve.yaml", "CURVE")]),
    "sphere": ("a sphere (10,000 points) and pull.yaml, its top pulled up and twisted",
               [("scans/sphere.ply", "sphere"), ("pull.yaml", "PULL")]),
    "rubber_sheet": ("a drifted terrain scan (60,000 points), 12 surveyed control points "
                     "(gcp.csv) and rubber_sheet.yaml, a points: edit warping it back",
                     [("scans/drifted_scan.ply", "drifted"), ("scans/gcp.csv", "gcp"),
                      ("rubber_sheet.yaml", "RUBBER_SHEET")]),
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("example", help="write an example scan and its edit config "
                                       "(the quick start: `splatdeform example bar`)")
    p.add_argument("name", nargs="?", metavar="NAME",
                   help="the example: " + ", ".join(EXAMPLES) + " (--list says what each is)")
    p.add_argument("dir", nargs="?", default=".", metavar="DIR",
                   help="the folder to write into (default: the current folder)")
    p.add_argument("--list", action="store_true", help="list the examples and their files")
    p.add_argument("--force", action="store_true",
                   help="replace files that exist with other contents (default: refuse)")
    p.set_defaults(func=cmd_example)


def _contents(maker: str, scratch: Path) -> bytes:
    if maker in ("drifted", "gcp"):   # the rubber-sheeting terrain (seeded)
        from splatdeform.io import save
        from splatdeform.model import PointModel

        from . import terrain

        true = terrain.truth()
        scan = terrain.drift(true)
        if maker == "gcp":
            return terrain.pairs_csv(true, scan).encode()
        return save(PointModel(positions=scan), scratch / "drifted.ply").read_bytes()
    if maker in ("bar", "sphere"):
        from splatdeform.io import save

        from . import scans

        model = scans.bumpy_bar() if maker == "bar" else scans.sphere()
        return save(model, scratch / f"{maker}.ply").read_bytes()
    from . import configs

    return getattr(configs, maker).encode()


def write_example(name: str, folder: str | Path, *, force: bool = False) -> list[Path]:
    """Write example ``name``'s files under ``folder``; returns their paths. A file that exists
    with the same contents is kept; with other contents it is refused (InputError, nothing
    written) unless ``force``."""
    import tempfile

    from splatdeform.io.atomic import atomic_write

    if name not in EXAMPLES:
        from splatdeform.suggest import did_you_mean

        raise InputError(f"example: unknown example {name!r}{did_you_mean(name, EXAMPLES)}; "
                         f"expected one of {', '.join(EXAMPLES)}")
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{folder}: expected a folder to write the example into")
    with tempfile.TemporaryDirectory(prefix="splatdeform-example-") as scratch:
        files = [(folder / rel, _contents(maker, Path(scratch)))
                 for rel, maker in EXAMPLES[name][1]]
    for path, data in files:
        if path.is_dir() or (path.exists() and not force and path.read_bytes() != data):
            raise InputError(f"{path}: exists with other contents; remove it, choose another "
                             "DIR or pass --force")
    for path, data in files:
        if not (path.is_file() and path.read_bytes() == data):
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(path) as stream:
                stream.write(data)
    return [path for path, _ in files]


def cmd_example(args: argparse.Namespace) -> int:
    if args.list:
        for name, (what, files) in EXAMPLES.items():
            print(f"{name:12s} {what}: {', '.join(f for f, _ in files)}")
        return 0
    if args.name is None:
        raise InputError(f"example: expected an example name ({', '.join(EXAMPLES)}) or --list")
    written = write_example(args.name, args.dir, force=args.force)
    print("wrote " + " and ".join(str(p) for p in written), file=sys.stdout)
    config = written[-1]
    print(f"next: splatdeform deform {config}")
    return 0
