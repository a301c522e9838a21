"""The interlock latch that outlives a run: after a latched fault nothing re-energises a rig until an operator
resets it, whether the next attempt is a run, a resumed campaign or manual control.

One JSON file per rig name in the bench's state folder (``$BENCH_STATE_DIR``, default
``~/.local/state/dea-bench``): ``interlock-<rig>-<hash>.json`` with the exact rig name, the fault, when it latched
and in which run file. The file name is the rig name made safe for a file name plus a short hash of the exact
name, so two rigs whose names differ only in punctuation or spaces never share a latch. A latch file of the
older form (``interlock-<rig>.json``, no hash) still counts for the rig whose exact name it records.
A bench before the hashed names reads only that older form, so a latch is written in both while the older file
is free or already this rig's (a latch under another name that cleans up alike is never replaced).
A real rig's latch also records its amplifier's drive path (``RigConfig.drive_path``: the set-point module's port
and unit, or the T7's address), and holds every rig file that drives the same hardware: renaming the rig, or a
copy of its file under another name, does not get round a latch.
Every latch and reset is also appended to ``interlock.log`` there (who, why, when), so the history survives
the reset.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shlex
from datetime import datetime
from pathlib import Path
from typing import Any

STATE_ENV = "BENCH_STATE_DIR"


class LatchedError(ValueError):
    """A rig whose interlock is latched: refused until an operator resets it (one line, names the command)."""


def state_dir() -> Path:
    """The bench's state folder (``$BENCH_STATE_DIR`` or ``~/.local/state/dea-bench``)."""
    env = os.environ.get(STATE_ENV)
    return Path(env) if env else Path.home() / ".local" / "state" / "dea-bench"


def _safe(rig_name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", rig_name)


def latch_path(rig_name: str) -> Path:
    """The latch file of rig ``rig_name``: one per exact name (the hash keeps names that clean up alike apart)."""
    digest = hashlib.sha256(rig_name.encode("utf-8", "surrogatepass")).hexdigest()[:12]
    return state_dir() / f"interlock-{_safe(rig_name)}-{digest}.json"


def _legacy_path(rig_name: str) -> Path:
    """Where a bench before the hashed names kept the latch of ``rig_name`` (shared by names that clean up
    alike; it records the exact name)."""
    return state_dir() / f"interlock-{_safe(rig_name)}.json"


def _read(path: Path) -> dict[str, Any] | None:
    """The latch in ``path``; None if it is unreadable or not a latch."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _legacy(rig_name: str) -> dict[str, Any] | None:
    """The old-format latch of ``rig_name``, if there is one and it is this rig's (or cannot say whose it is:
    an unreadable latch counts as latched)."""
    path = _legacy_path(rig_name)
    if not path.exists():
        return None
    data = _read(path)
    if data is None or not isinstance(data.get("rig"), str):
        return {"rig": rig_name, "fault": f"latch file {path} unreadable", "where": "?", "at": "?"}
    return data if data["rig"] == rig_name else None


def _now() -> str:
    return datetime.now().astimezone().isoformat(timespec="seconds")


def _history(line: str) -> None:
    with (state_dir() / "interlock.log").open("a", encoding="utf-8") as fh:
        fh.write(f"{_now()}\t{line}\n")


def _write(path: Path, record: dict[str, Any]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(record), encoding="utf-8")
    os.replace(tmp, path)


def latch(rig_name: str, fault: str, where: str, drive: str | None = None) -> Path:
    """Latch rig ``rig_name`` after ``fault`` (one line) seen in ``where`` (a run file or a manual session);
    ``drive``: the amplifier's drive path of a real rig (``RigConfig.drive_path``), which the latch holds too."""
    path = latch_path(rig_name)
    path.parent.mkdir(parents=True, exist_ok=True)
    record: dict[str, Any] = {"rig": rig_name, "fault": fault, "where": where, "at": _now()}
    if drive is not None:
        record["drive"] = drive
    _write(path, record)
    old = _legacy_path(rig_name)
    mine = (_read(old) or {}).get("rig") == rig_name if old.exists() else True  # free, or this rig's (readable)
    if mine:  # an older bench sees it too
        _write(old, record)
    _history(f"latched\t{rig_name}\t{fault}\t{where}")
    return path


def _own(rig_name: str) -> dict[str, Any] | None:
    path = latch_path(rig_name)
    if not path.exists():
        return _legacy(rig_name)
    data = _read(path)
    if data is not None:
        return data
    return {"rig": rig_name, "fault": f"latch file {path} unreadable", "where": "?", "at": "?"}


def latched(rig_name: str, drive: str | None = None) -> dict[str, Any] | None:
    """The latch of rig ``rig_name`` (fault, where, at), or else a latch of any rig on the same amplifier drive
    path ``drive`` (its ``rig`` names the rig it was latched under), or None. An unreadable latch file counts as
    latched."""
    own = _own(rig_name)
    if own is not None or drive is None:
        return own
    for was in all_latched().values():
        if was.get("drive") == drive:
            return was
    return None


def all_latched() -> dict[str, dict[str, Any]]:
    """Every latch in the state folder, by exact rig name (as its file records it; the file name if it cannot
    be read)."""
    found: dict[str, dict[str, Any]] = {}
    for path in sorted(state_dir().glob("interlock-*.json")):
        data = _read(path)
        if data is None or not isinstance(data.get("rig"), str):
            name = path.stem.removeprefix("interlock-")
            data = {"rig": name, "fault": f"latch file {path} unreadable", "where": "?", "at": "?"}
        found.setdefault(data["rig"], data)
    return found


def reset(rig_name: str, by: str, why: str, drive: str | None = None) -> dict[str, Any] | None:
    """Reset the latch that :func:`latched` finds for ``rig_name`` and ``drive`` (an operator's explicit act: ``by``
    and ``why`` required, recorded in the history); returns what was latched, or None if nothing was."""
    if not by.strip() or not why.strip():
        raise ValueError("resetting the interlock needs who (--operator) and why (--why)")
    was = latched(rig_name, drive)
    if was is None:
        return None
    name = was["rig"] if isinstance(was.get("rig"), str) else rig_name
    latch_path(name).unlink(missing_ok=True)
    if _legacy(name) is not None:
        _legacy_path(name).unlink(missing_ok=True)
    via = "" if name == rig_name else f" (latched under rig {name}, the same amplifier drive {drive})"
    _history(f"reset\t{name}\tby {by}: {why}{via}\t(was: {was.get('fault')} in {was.get('where')})")
    return was


def refuse_if_latched(rig_name: str, drive: str | None = None) -> None:
    """LatchedError (one line) while rig ``rig_name``, or another rig on its amplifier drive path, is latched."""
    was = latched(rig_name, drive)
    if was is None:
        return
    name = was["rig"] if isinstance(was.get("rig"), str) else rig_name
    who = f"rig {rig_name}:" if name == rig_name else f"rig {rig_name}: its amplifier drive ({drive}) is latched " \
        f"under rig {name};"
    raise LatchedError(f"{who} interlock latched at {was.get('at')} ({was.get('fault')}; in "
                       f"{was.get('where')}): nothing energises it until an operator resets it — "
                       f"bench interlock reset {shlex.quote(name)} --why '…', or bench run --resume RUN.h5 "
                       "--why '…'")
