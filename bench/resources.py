"""The protocol and rig files shipped with dea-bench, found through :mod:`importlib.resources`.

They live in the package ``bench.data`` (``protocols/``, ``protocols/short/``, ``protocols/protocol.schema.json``
and ``rigs/``), so an installed wheel finds them wherever it runs; a protocol's ``rig = "../rigs/…"`` resolves
inside the package as it does in the repository.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

SCHEMA_NAME = "protocol.schema.json"


def data_dir() -> Path:
    """Folder of the shipped files (``protocols/`` and ``rigs/`` below it)."""
    root = files("bench.data")
    if not isinstance(root, Path):  # a zip import: the engine needs real files (rig paths resolve on disk)
        raise OSError("dea-bench's data files are not on a file system: install the package unzipped")
    return root


def protocols_dir() -> Path:
    """Folder of the shipped protocol files (the papers' campaigns; ``short/`` holds the CI variants)."""
    return data_dir() / "protocols"


def rigs_dir() -> Path:
    """Folder of the shipped rig files (simulated rigs and lab templates)."""
    return data_dir() / "rigs"


def shipped_protocols() -> dict[str, Path]:
    """Shipped protocol files by name: ``thesis-identification``, ``short/thesis-identification-short`` …"""
    root = protocols_dir()
    return {p.relative_to(root).with_suffix("").as_posix(): p for p in sorted(root.rglob("*.toml"))}


def shipped_rigs() -> dict[str, Path]:
    """Shipped rig files by name (``thesis-sim``, ``lsdea-motor-lab`` …)."""
    return {p.stem: p for p in sorted(rigs_dir().glob("*.toml"))}


def _pick(known: dict[str, Path], name: str, kind: str) -> Path:
    """A shipped file by its listed name, or by an unambiguous base name (``thesis-identification-short``, also
    written as a path such as ``protocols/short/thesis-identification-short.toml``)."""
    key = name.replace("\\", "/").removesuffix(".toml")
    for prefix in ("protocols/", "rigs/"):
        key = key.removeprefix(prefix)
    if key in known:
        return known[key]
    base = key.rsplit("/", 1)[-1]
    matches = [k for k in known if k.rsplit("/", 1)[-1] == base]
    if len(matches) == 1:
        return known[matches[0]]
    if matches:
        raise ValueError(f"shipped {kind} {name!r} is ambiguous: {', '.join(matches)}")
    raise ValueError(f"no shipped {kind} {name!r}: one of {', '.join(known)}")


def protocol(name: str) -> Path:
    """A shipped protocol by name or unambiguous base name (with or without ``.toml``); ValueError naming the
    choices otherwise."""
    return _pick(shipped_protocols(), name, "protocol")


def rig(name: str) -> Path:
    """A shipped rig file by name (with or without ``.toml``); ValueError naming the choices otherwise."""
    return _pick(shipped_rigs(), name, "rig")
