"""TAB completion of protocol and rig files and of the shipped protocols' names (typer ``autocompletion``).

Each TAB runs ``bench`` again, so these read file names and a file's first lines only: no model, no TOML parser.
A file argument completes to the folders and the ``.toml`` files of the right kind beside what is typed (a lab
folder's ``protocols/`` and ``rigs/``, the repository's); a name argument (``bench protocols show``) to the
names of the shipped protocols.
"""

from __future__ import annotations

import re
from pathlib import Path

# a protocol file has a [protocol] table (its name, rig, description); a rig file has [specimen] and none
_PROTOCOL = re.compile(r"^\s*\[protocol\]", re.MULTILINE)
_RIG = re.compile(r"^\s*\[specimen\]", re.MULTILINE)
HEAD_BYTES = 4096  # enough for the comments above a file's first table


def _kind(path: Path) -> str | None:
    """``"protocol"``, ``"rig"`` or None, from the first lines of a TOML file."""
    try:
        with path.open(encoding="utf-8", errors="replace") as f:
            head = f.read(HEAD_BYTES)
    except OSError:
        return None
    if _PROTOCOL.search(head):
        return "protocol"
    return "rig" if _RIG.search(head) else None


def _files(incomplete: str, kind: str) -> list[str]:
    """Folders and ``kind`` files whose path starts with ``incomplete`` (as typed: relative or absolute)."""
    folder, _, stem = incomplete.rpartition("/")
    base = Path(folder or ".") if not incomplete.startswith("/") or folder else Path("/")
    prefix = f"{folder}/" if folder or incomplete.startswith("/") else ""
    try:
        entries = sorted(base.iterdir())
    except OSError:
        return []
    out = []
    for entry in entries:
        if not entry.name.startswith(stem) or (entry.name.startswith(".") and not stem.startswith(".")):
            continue
        if entry.is_dir():
            out.append(f"{prefix}{entry.name}/")
        elif entry.suffix == ".toml" and _kind(entry) == kind:
            out.append(f"{prefix}{entry.name}")
    return out


def protocol_files(incomplete: str) -> list[str]:
    """Completion of a protocol file argument."""
    return _files(incomplete, "protocol")


def rig_files(incomplete: str) -> list[str]:
    """Completion of a rig file argument or option."""
    return _files(incomplete, "rig")


def protocol_names(incomplete: str) -> list[str]:
    """Completion of a shipped protocol's name (``bench protocols show|copy NAME``)."""
    from bench.resources import shipped_protocols

    return [name for name in shipped_protocols() if name.startswith(incomplete)]
