"""Output files the commands write (exports, figures, rig files): never a silent replacement, never a cut-off file.

A file the user names (``--mat F``, ``--export F``, ``plot --out F.png``) is a new file: an existing one is refused
in one line (:func:`refuse_existing`), before the work. A folder of a run's outputs (``export --csv``, ``report``)
holds one run: a marker file names it, and another run's outputs there are refused (:func:`claim_folder`); the same
run's are replaced. Every output is written to a temporary file in its own
folder and moved into place only once complete (:func:`atomic_output`): a failure mid-write (a full disk, an
exception) removes the temporary and leaves the target as it was, so a retry is not refused by a half file.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import secrets
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from bench.storage.recorder import cause

NO_HARD_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.ENOSYS, errno.EMLINK}
# a marker's keys that change as a run ends or name the outputs (not the run's identity)
VOLATILE = {"state", "reason", "complete", "export_files", "report_files", "end_time", "exit_status", "exit_reason"}


def refuse_existing(target: Path, command: str, label: str = "", example: str = "out") -> None:
    """Refuse ``target`` as a new file in one line naming it (``label`` before it, e.g. ``--export``): a folder (a
    name in it, ``example``, suggested), or an existing file (``bench COMMAND does not overwrite files``)."""
    name = f"{label} {target}" if label else str(target)
    if target.is_dir():
        raise IsADirectoryError(f"{name}: a folder; give the file's name (e.g. {target / example})")
    if target.exists() or target.is_symlink():
        raise FileExistsError(f"{name}: exists; bench {command} does not overwrite files: choose another name")


def _temporary(target: Path) -> Path:
    """A new empty file beside ``target`` (same folder: the move is a rename), hidden, with its file type (the
    writers that infer the format from it, matplotlib's, see the same), mode as the umask gives a new file."""
    while True:
        tmp = target.with_name(f".{target.stem[:64]}.{secrets.token_hex(4)}.part{target.suffix}")  # a long name fits
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            continue
        return tmp


@contextlib.contextmanager
def atomic_output(target: Path, *, replace: bool = False) -> Iterator[Path]:
    """Yield a temporary path to write ``target``'s content to; on success it becomes ``target`` — replacing an
    existing file only with ``replace`` (else FileExistsError naming it, also for one made meanwhile: a hard link
    never replaces) — and on any failure it is removed, ``target`` left as it was."""
    tmp = _temporary(target)
    try:
        yield tmp
        if replace:
            with contextlib.suppress(OSError):  # the file it replaces keeps its permissions (a 640 stays 640)
                shutil.copymode(target, tmp)
            os.replace(tmp, target)
            return
        try:
            os.link(tmp, target)
        except FileExistsError:
            raise FileExistsError(f"{target}: exists; it was made while this was written: choose another "
                                  "name") from None
        except OSError as exc:  # a file system without hard links: checked, then renamed
            if exc.errno not in NO_HARD_LINKS:
                raise
            if target.exists() or target.is_symlink():
                raise FileExistsError(f"{target}: exists; it was made while this was written: choose another "
                                      "name") from None
            os.replace(tmp, target)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def write_text(target: Path, text: str, *, replace: bool = False) -> None:
    """Write ``text`` (UTF-8) to ``target`` through :func:`atomic_output`."""
    with atomic_output(target, replace=replace) as tmp:
        tmp.write_text(text, encoding="utf-8")


def same_run(meta: dict[str, Any], run: dict[str, Any]) -> bool:
    """Whether a marker's run metadata (``meta``) is of the run whose metadata is ``run``: the same ``run_id``;
    for files older than run ids, the same attributes but those that change as a run ends."""
    ours, theirs = str(run.get("run_id") or ""), str(meta.get("run_id") or "")
    if ours or theirs:
        return ours == theirs
    return {k: v for k, v in meta.items() if k not in VOLATILE} == \
        {k: v for k, v in json.loads(json.dumps(run, default=str)).items() if k not in VOLATILE}


def claim_folder(out: Path, marker: str, run: dict[str, Any], command: str, what: str,
                 loose: list[str]) -> dict[str, Any] | None:
    """Check that folder ``out`` may take ``what`` (``export``, ``report``) of the run whose metadata is ``run``: no
    folder yet, one without its ``marker`` file and without ``loose`` (the names of such outputs found there), or
    one whose ``marker`` names the same run (its content returned: the earlier outputs are replaced). Another run's,
    or outputs without a marker: FileExistsError, one line naming ``out``; a file there, not a folder: likewise
    (an outside tester: `--out RUN.h5` said "[Errno 17] File exists")."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: a file, not a folder for the {what}: give a folder (a new one is made)")
    if not out.is_dir():
        return None
    refuse = f"; bench {command} does not mix runs in a folder: choose an empty or new folder (or remove {out})"
    meta_path = out / marker
    if not meta_path.exists():
        if loose:
            raise FileExistsError(f"{out}: holds {', '.join(loose[:3])}{' …' if len(loose) > 3 else ''} of no "
                                  f"{what} of this run (no {marker}){refuse}")
        return None
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise FileExistsError(f"{out}: holds a {marker} that is no {what}'s ({cause(exc)}){refuse}") from None
    if not isinstance(meta, dict):
        raise FileExistsError(f"{out}: holds a {marker} that is no {what}'s{refuse}")
    if not same_run(meta, run):
        other = f"run_id {meta['run_id']}" if meta.get("run_id") else f"protocol {meta.get('protocol_name', '?')}"
        raise FileExistsError(f"{out}: holds the {what} of another run ({other}){refuse}")
    return meta
