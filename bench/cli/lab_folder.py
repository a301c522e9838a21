"""A lab's working folder: copies of the shipped protocol and rig files, editable, comments kept.

``bench init DIR`` lays out ``DIR/rigs/*.toml``, ``DIR/protocols/**.toml`` (with the JSON schema) and
``DIR/runs/``; the protocols' ``rig = "../rigs/…"`` then names the lab's own rig files. A single protocol
copied elsewhere (``bench protocols copy``) gets its ``rig`` rewritten so that it still names a rig file.
"""

from __future__ import annotations

import os
import shutil
import tomllib
from dataclasses import dataclass
from pathlib import Path

import tomlkit

from bench.resources import protocols_dir, rigs_dir, shipped_protocols

LAB_README = """\
# dea-bench lab folder

Made by `bench init`. Edit the files here; the shipped originals stay untouched.

* `rigs/`       rig files: `*-sim.toml` are simulated twins, `*-lab.toml` templates for the real bench
                (set `port`, calibration and limits, then `bench devices check rigs/<rig>.toml`)
* `protocols/`  protocol files of the papers' campaigns (`short/`: short variants), schema for editors
* `runs/`       run files (`bench run protocols/<file>.toml` writes here)

    bench validate protocols/thesis-identification.toml
    bench run protocols/thesis-identification.toml --virtual-time
    bench inspect runs/<file>.h5
    bench export runs/<file>.h5 --csv runs/<file>-csv
"""


@dataclass(frozen=True)
class ProtocolInfo:
    """A shipped protocol: name, description, rig file name and path."""

    name: str
    description: str
    rig: str
    path: Path


def protocol_infos() -> list[ProtocolInfo]:
    """Every shipped protocol with its description and rig."""
    out = []
    for name, path in shipped_protocols().items():
        table = tomllib.loads(path.read_text(encoding="utf-8")).get("protocol", {})
        out.append(ProtocolInfo(name, str(table.get("description", "")), Path(str(table.get("rig", ""))).stem,
                                path))
    return out


def _copy(src: Path, dst: Path, written: list[Path]) -> None:
    if dst.exists():
        raise FileExistsError(f"{dst}: exists; bench init does not overwrite files")
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    written.append(dst)


def init_lab(folder: Path) -> list[Path]:
    """Lay out a lab folder (see module docstring); refuses to overwrite any file. Returns the files written."""
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{folder}: not a folder")
    written: list[Path] = []
    src_protocols, src_rigs = protocols_dir(), rigs_dir()
    todo = [(p, folder / "protocols" / p.relative_to(src_protocols)) for p in sorted(src_protocols.rglob("*"))
            if p.is_file() and p.suffix in (".toml", ".json", ".md")]
    todo += [(p, folder / "rigs" / p.name) for p in sorted(src_rigs.glob("*.toml"))]
    clashes = [dst for _, dst in todo if dst.exists()]
    if clashes:
        raise FileExistsError(f"{clashes[0]}: exists ({len(clashes)} files would be overwritten); bench init "
                              "does not overwrite files: choose an empty or new folder")
    for src, dst in todo:
        _copy(src, dst, written)
    (folder / "runs").mkdir(parents=True, exist_ok=True)
    readme = folder / "README.md"
    if not readme.exists():
        readme.write_text(LAB_README, encoding="utf-8")
        written.append(readme)
    return written


def copy_protocol(src: Path, dest: Path, rig: Path | None = None) -> Path:
    """Copy a protocol file (comments kept), pointing its ``rig`` at a rig file that exists from ``dest``.

    ``dest`` is a file or an existing folder. The rig is ``rig`` if given; else the original's rig, looked
    for first in the lab folder the copy lands in (``rigs/<name>.toml`` in the nearest folder above the copy
    that has it: ``../rigs/`` from ``protocols/``, ``../../rigs/`` from ``protocols/short/``), then the shipped one —
    written as a relative path within a lab folder, by its name for a shipped rig (found wherever bench is
    installed), else as an absolute path.
    """
    from bench.protocol.schema import resolve_rig_ref
    from bench.resources import shipped_rigs

    target = dest / src.name if dest.is_dir() else dest
    if target.exists():
        raise FileExistsError(f"{target}: exists; choose another name")
    doc = tomlkit.parse(src.read_text(encoding="utf-8"))
    table = doc.get("protocol")
    if table is None or "rig" not in table:
        raise ValueError(f"protocol file {src}: no [protocol] rig to point at")
    original = resolve_rig_ref(src.parent, str(table["rig"]))
    here = target.parent.resolve()
    if rig is None:
        # the lab folder the copy lands in (protocols/, protocols/short/ …): the nearest folder above with the rig
        local = next((d / "rigs" / original.name for d in (here, *here.parents)
                      if (d / "rigs" / original.name).is_file()), None)
        rig = local if local is not None else original
    if not rig.is_file():
        from bench.app.runs import rig_suggestion

        raise FileNotFoundError(f"rig file {rig}: not found{rig_suggestion(rig)}")
    target.parent.mkdir(parents=True, exist_ok=True)
    rig_abs = rig.resolve()
    # relative within a lab folder (../rigs/x.toml, ../../rigs/x.toml), absolute otherwise (the shipped rig, or a
    # rig far away)
    in_lab = here == rig_abs.parent or here.is_relative_to(rig_abs.parent.parent)
    shipped = shipped_rigs().get(rig_abs.stem)
    if in_lab:
        text = Path(os.path.relpath(rig_abs, here)).as_posix()
    elif shipped is not None and shipped.resolve() == rig_abs:  # by name: found wherever bench is installed
        text = rig_abs.stem
    else:  # a rig far away
        text = rig_abs.as_posix()
    table["rig"] = text
    target.write_text(tomlkit.dumps(doc), encoding="utf-8")
    return target
