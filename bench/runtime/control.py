"""A run's control file: how ``bench pause`` and ``bench resume`` reach a run from another terminal.

``RUN.control`` beside ``RUN.h5`` holds one JSON object: ``{"pause": true|false, "by": "...", "why": "...",
"at": "ISO time"}``, and ``"stop": true`` to end the run (``bench watch``'s stop button: the run goes safe as on
Ctrl-C, the stop recorded with who asked). The engine looks at the file's stamp (time, inode) every
:data:`CONTROL_POLL_S` of wall time and reads it when it changed. A file that cannot be read or parsed changes
nothing (the run goes on as it was): a half-written file is read again at the next look.
"""

from __future__ import annotations

import json
import os
from datetime import datetime
from pathlib import Path

CONTROL_POLL_S = 0.1  # wall time between two looks at the control file


def control_path(run_file: str | Path) -> Path:
    """The control file of a run file: ``RUN.control`` beside ``RUN.h5``."""
    return Path(run_file).with_suffix(".control")


def write_control(run_file: str | Path, pause: bool, by: str, why: str, stop: bool = False) -> Path:
    """Ask the run writing ``run_file`` to pause (or to resume, or with ``stop`` to end); atomic (written beside,
    then renamed). A stop also says pause, so a run that reads it in a pause stays at 0 V until it ends."""
    path = control_path(run_file)
    tmp = path.with_suffix(".control.tmp")
    at = datetime.now().astimezone().isoformat()
    word: dict[str, object] = {"pause": pause or stop, "by": by, "why": why, "at": at}
    if stop:
        word["stop"] = True
    text = json.dumps(word)
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


FileStamp = tuple[int, int, int]  # the control file's (mtime in ns, inode, size): which word it holds
ControlWord = tuple[FileStamp, bool, str, bool]  # the control file's (stamp, pause?, "by (why)", stop?)
NO_WORD: ControlWord = ((0, 0, 0), False, "", False)


def read_control(path: Path, seen: ControlWord) -> ControlWord:
    """(stamp, pause?, "by (why)", stop?) of the control file; ``seen`` when it is absent, unchanged or unreadable.

    A word is new when the file's stamp changed: its modification time to the nanosecond, and its inode — every word
    is a new file renamed into place — since some filesystems keep the time in whole seconds (FAT: two), and a
    second word within that time had the first's and was never seen (found in review)."""
    try:
        st = path.stat()
    except OSError:
        return seen
    mtime = (st.st_mtime_ns, st.st_ino, st.st_size)
    if mtime == seen[0]:
        return seen
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        pause = data["pause"]
        stop = data.get("stop", False)
        if not isinstance(pause, bool) or not isinstance(stop, bool):
            return seen
        who = f"{data.get('by') or 'someone'} (control file{': ' + str(data['why']) if data.get('why') else ''})"
    except (OSError, ValueError, KeyError, TypeError):
        return seen
    return mtime, pause, who, stop
