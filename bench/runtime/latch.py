"""The interlock latch that outlives a run: after a latched fault nothing re-energises a rig until an operator
resets it, whether the next attempt is a run, a resumed campaign or manual control.

One JSON file per rig name in the bench's state folder (``$BENCH_STATE_DIR``, default
``~/.local/state/dea-bench``): ``interlock-<rig>-<hash>.json`` with the exact rig name, the fault, when it latched
and in which run file. The file name is the rig name made safe for a file name plus a short hash of the exact
name, so two rigs whose names differ only in punctuation or spaces never share a latch. A latch file of the
older form (``interlock-<rig>.json``, no hash) still counts for the rig whose exact name it records.
A bench before the hashed names reads only that older form, so a latch is written in both while the older file
is free or already this rig's (a latch under another name that cleans up alike is never replaced).
A real rig's latch also records its amplifier's drive (:func:`drive_of`: the set-point module's port, unit and
channel, or the T7's address and DAC, under every name this machine knows for it), and holds every rig file that
drives the same hardware: renaming the rig, copying its file under another name, or naming the port another way
(a ``/dev/serial/by-id`` link, a host name in other letters) does not get round a latch. A host name and its IP
address are not matched: no name server is asked before a start.
Every latch and reset is also appended to ``interlock.log`` there (who, why, when), so the history survives
the reset.

A process that energises a rig (a run, a manual-control session) first leaves an *armed* marker there
(``armed-<rig>-<hash>-<pid>-<token>.json``: the rig, its process ID, boot ID and start time, the run file or session
log) and removes it only once its shutdown has commanded and verified 0 V, or latched the rig. Until then the
process holds an ``flock`` on the marker, which the kernel releases when the process ends however it ends: whatever
its process ID means in another PID namespace, and whatever its container's host name is now. A marker whose lock is
free is a bench that ended without its shutdown (``kill -9``, a power cut, a crash): the next look at the latches (a
start, ``bench interlock status``) turns it into a latch of its rig, so nothing energises the rig again until an
operator resets it. Where there is no ``flock`` (Windows, some network mounts, a marker of a bench before the locks)
its process ID, start time and boot decide (on Windows without ``os.kill``, which would end the process), and one
armed on another host is taken as running; ``bench interlock status`` lists the markers taken as running too. A
look by a user who may only read the folder reports a dead marker as latched without writing the latch.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import ipaddress
import json
import os
import re
import shlex
import socket
import sys
import uuid
from collections.abc import Collection
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlsplit

if TYPE_CHECKING:
    from bench.rig import RigConfig

STATE_ENV = "BENCH_STATE_DIR"
SERIAL_LINKS = (Path("/dev/serial/by-id"), Path("/dev/serial/by-path"))  # udev's stable names of serial adapters


class LatchedError(ValueError):
    """A rig whose interlock is latched: refused until an operator resets it (one line, names the command)."""


@dataclass(frozen=True)
class Drive:
    """A real rig's amplifier drive: as its rig file gives it (``text``) and every name of it this machine knows
    (``ids``: a latch holds any rig whose drive shares one)."""

    text: str
    ids: frozenset[str]


def _host(host: str) -> str:
    """A host as one spelling: an IP address in its compressed form, a name in lower case."""
    try:
        return ipaddress.ip_address(host.strip("[]")).compressed
    except ValueError:
        return host.lower()


def _port_names(port: str) -> set[str]:
    """A port's names: a serial device as written, resolved, and every ``/dev/serial`` link to it (a replugged
    adapter keeps its by-id name when its number changes); a URL's host as :func:`_host` spells it."""
    if "://" in port:
        try:
            url = urlsplit(port)
            number = f":{url.port}" if url.port is not None else ""
        except ValueError:  # not a URL pyserial would open either: the text as it is
            return {port.lower()}
        return {f"{url.scheme.lower()}://{_host(url.hostname or '')}{number}"}
    if not os.path.isabs(port) and "/" not in port and "\\" not in port:  # a device name: COM3 (Windows, any case)
        return {port.upper()}
    real = os.path.realpath(port)
    names = {port, real}
    for folder in SERIAL_LINKS:
        try:
            names.update(str(link) for link in folder.iterdir() if os.path.realpath(link) == real)
        except OSError:
            continue
    return names


def drive_of(rig: RigConfig) -> Drive | None:
    """The amplifier drive of a real rig (None: a simulated rig, whose twins are its own, or no amplifier)."""
    text = rig.drive_path()
    amp = rig.amplifier
    if text is None or amp is None:
        return None
    if amp.drive == "daq" and rig.daq is not None:
        return Drive(text, frozenset({f"tcp://{_host(rig.daq.host)}:{rig.daq.port} DAC{rig.daq.dac}"}))
    bus = rig.buses.get(amp.bus)
    names = _port_names(bus.port) if bus is not None else {amp.bus}
    return Drive(text, frozenset(f"{n} unit {amp.ao_unit} channel {amp.ao_channel}" for n in names))


def _on(was: dict[str, Any], drive: Drive) -> bool:
    """Whether the latch ``was`` holds ``drive`` (a latch from before the drive's names: by its text)."""
    ids = was.get("drive_ids")
    if isinstance(ids, list) and drive.ids & {str(i) for i in ids}:
        return True
    return was.get("drive") == drive.text


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
        return {"rig": rig_name, "fault": f"latch file {path} unreadable", "where": "?", "at": "?",
                "unreadable": str(path)}
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


def latch(rig_name: str, fault: str, where: str, drive: Drive | None = None) -> Path:
    """Latch rig ``rig_name`` after ``fault`` (one line) seen in ``where`` (a run file or a manual session);
    ``drive``: a real rig's amplifier drive (:func:`drive_of`), which the latch holds too."""
    path = latch_path(rig_name)
    path.parent.mkdir(parents=True, exist_ok=True)
    record: dict[str, Any] = {"rig": rig_name, "fault": fault, "where": where, "at": _now()}
    if drive is not None:
        record["drive"], record["drive_ids"] = drive.text, sorted(drive.ids)
    _write(path, record)
    old = _legacy_path(rig_name)
    mine = (_read(old) or {}).get("rig") == rig_name if old.exists() else True  # free, or this rig's (readable)
    if mine:  # an older bench sees it too
        _write(old, record)
    _history(f"latched\t{rig_name}\t{fault}\t{where}")
    return path


def note(line: str) -> None:
    """One line in the interlock history (``interlock.log``) that is neither a latch nor a reset."""
    state_dir().mkdir(parents=True, exist_ok=True)
    _history(line)


# ---------------------------------------------------------------- armed markers: a bench that died energised
def _boot_id() -> str:
    """This boot of the machine (Linux; '' elsewhere): a process ID from another boot names another process."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text(encoding="ascii").strip()
    except OSError:
        return ""


def _started(pid: int) -> str:
    """When process ``pid`` started, in clock ticks since boot (field 22 of ``/proc/PID/stat``; '' if unknown, and
    on Windows, which has no ``/proc``: the test that pretends to be Windows on Linux read another process's start
    there and took a live marker for a reused ID whenever a process 4242 happened to exist)."""
    if sys.platform == "win32":
        return ""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text(encoding="ascii", errors="replace")
    except OSError:
        return ""
    fields = stat[stat.rfind(")") + 2:].split()  # after the command name, which may hold spaces and parentheses
    return fields[19] if len(fields) > 19 else ""


def _running(pid: int) -> bool:
    """Whether a process with ID ``pid`` exists (never a latch on a guess: True where it cannot be told)."""
    if sys.platform == "win32":  # os.kill on Windows terminates the process, whatever the signal: never called
        import ctypes
        from ctypes import wintypes

        try:  # the error of the last call as Windows set it (ctypes.get_last_error), not what a later call left
            kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)
        except (AttributeError, OSError):  # no Windows API after all: cannot tell
            return True
        kernel32.OpenProcess.restype = wintypes.HANDLE
        kernel32.OpenProcess.argtypes = (wintypes.DWORD, wintypes.BOOL, wintypes.DWORD)
        handle = kernel32.OpenProcess(0x1000, False, pid)  # PROCESS_QUERY_LIMITED_INFORMATION: reads, ends nothing
        if not handle:
            return ctypes.get_last_error() != 87  # ERROR_INVALID_PARAMETER: no such process; else (denied) it exists
        code = ctypes.c_ulong()
        try:
            if not kernel32.GetExitCodeProcess(handle, ctypes.byref(code)):
                return True
        finally:
            kernel32.CloseHandle(handle)
        return code.value == 259  # STILL_ACTIVE
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: it exists
        return True
    except OSError:
        return True  # cannot tell: taken as running (never a latch on a guess)
    return True


def _flock(fd: int, exclusive: bool) -> bool | None:
    """A non-blocking ``flock`` on ``fd``: True taken, False another open file holds it, None no ``flock`` here
    (Windows, some network or FUSE mounts)."""
    if sys.platform == "win32":
        return None
    import fcntl

    try:
        fcntl.flock(fd, (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:
        return None
    return True


def _lock_free(path: Path) -> bool | None:
    """Whether the ``flock`` its arming process holds on marker ``path`` is free (True: that process ended, however
    it ended; the kernel released it), held (False: it runs, in whatever PID namespace or under whatever host name),
    or None: it cannot be told here (no ``flock``, the file cannot be opened)."""
    if sys.platform == "win32":
        return None
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)  # read only: a reader of the folder may ask
    except FileNotFoundError:
        return False  # disarmed meanwhile: nothing to latch
    except OSError:
        return None
    try:
        got = _flock(fd, exclusive=False)  # shared: two lookers at once do not take each other for the owner
        if got and os.fstat(fd).st_nlink == 0:  # disarmed between the open and the lock (the owner unlinks, then
            return False  # releases): a clean end, not a dead bench (a reviewer's forced interleaving latched it)
    finally:
        os.close(fd)
    return got


def _alive(was: dict[str, Any], path: Path) -> tuple[bool, str]:
    """Whether the process that left armed marker ``was`` (in ``path``) still runs, and how that was judged.
    The marker's ``flock`` decides where it has one; else (Windows, a bench before the locks, a folder without
    ``flock``) its process ID, start time and boot, and one on another host cannot be asked: taken as running."""
    if was.get("flock") is True:
        free = _lock_free(path)
        if free is not None:
            return not free, "holds its marker's lock"
    pid = was.get("pid")
    if was.get("host") not in (None, socket.gethostname()):
        return True, f"on another host ({was.get('host')}): cannot be checked from here, taken as running"
    if not isinstance(pid, int):
        return True, "no process ID in its marker: taken as running"
    boot = _boot_id()
    if was.get("boot") and boot and was["boot"] != boot:  # the machine restarted since
        return False, ""
    if not _running(pid):
        return False, ""
    now = _started(pid)
    if was.get("started") and now and was["started"] != now:  # the ID reused by another process
        return False, ""
    how = "its process ID runs" + (" (Windows: not told from a reused ID)" if sys.platform == "win32" else "")
    return True, how


_held: dict[Path, int] = {}  # this process's armed markers: the descriptor that holds each one's flock until disarm


def arm(rig_name: str, where: str, drive: Drive | None = None) -> Path:
    """Leave the marker that this process is about to energise rig ``rig_name`` (``where``: its run file or session
    log); :func:`disarm` it once the shutdown commanded and verified 0 V (or latched the rig). The process holds an
    ``flock`` on the marker until then: the kernel releases it when the process ends, however it ends, and a look at
    the latches that can take it knows the bench died energised."""
    pid = os.getpid()
    path = latch_path(rig_name)
    # one marker per start: two runs of one process on one rig (threads) never remove each other's
    path = path.with_name(f"armed-{path.stem.removeprefix('interlock-')}-{pid}-{uuid.uuid4().hex[:8]}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
    try:
        locked = _flock(fd, exclusive=True) is True  # locked before it has its name: no look finds it unlocked
        record: dict[str, Any] = {"rig": rig_name, "pid": pid, "started": _started(pid), "boot": _boot_id(),
                                  "host": socket.gethostname(), "where": where, "at": _now(), "flock": locked}
        if drive is not None:
            record["drive"], record["drive_ids"] = drive.text, sorted(drive.ids)
        data = json.dumps(record).encode("utf-8")
        while data:
            data = data[os.write(fd, data):]
        if not locked:  # nothing to hold; and Windows renames no file open without delete sharing (WinError 32)
            os.close(fd)
            fd = -1
        os.replace(tmp, path)
    except BaseException:
        if fd >= 0:
            os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    if locked:
        _held[path] = fd
    return path


def _forget_held() -> None:
    """In a forked child: close the copies of this process's marker descriptors. An flock belongs to the open file,
    which a fork shares: a child that kept a copy (``multiprocessing``'s fork start) held a killed bench's lock and
    its marker read as running until the child ended (a reviewer's repro). ``subprocess`` children inherit none."""
    for fd in _held.values():
        with contextlib.suppress(OSError):
            os.close(fd)
    _held.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_held)


def release(marker: Path | None) -> None:
    """Let go of an armed marker's lock but leave the file: the process could not record how its use of the rig
    ended (the latch not written), so the next look at the latches finds the marker unlocked and latches the rig —
    where a lock kept for the rest of a long-lived process would read as a bench still running."""
    fd = _held.pop(marker, None) if marker is not None else None
    if fd is not None:
        os.close(fd)


def note_paused(marker: Path | None, verified: str | None) -> None:
    """Say in this process's armed marker that the run is paused with 0 V verified (``verified``: how, the pause's
    ``verify`` event) or, None, that it goes on: a process killed while paused then latches its rig saying so — the
    latch is kept (nothing verified the output since), but it said "zero neither commanded nor verified" of a
    pause that had zeroed it (an outside tester). Best effort: the marker as it was where it cannot be written."""
    fd = _held.get(marker) if marker is not None else None
    if fd is None or not hasattr(os, "pread"):  # (Windows: no positioned read; the marker stays as armed)
        return
    with contextlib.suppress(OSError, ValueError):
        record = json.loads(os.pread(fd, 1 << 16, 0))
        record.pop("paused", None)
        if verified is not None:
            record["paused"] = verified
        data = json.dumps(record).encode("utf-8")
        os.pwrite(fd, data.ljust(os.fstat(fd).st_size), 0)  # over the old bytes, never shorter (JSON ends in spaces)


def disarm(marker: Path | None) -> None:
    """Remove an armed marker (:func:`arm`): the process ended its use of the rig with 0 V verified, or latched it."""
    if marker is not None:
        marker.unlink(missing_ok=True)  # first: with its lock released but the file there, it would read as dead
        fd = _held.pop(marker, None)
        if fd is not None:
            os.close(fd)


def _markers() -> list[tuple[Path, dict[str, Any]]]:
    found = []
    for path in sorted(state_dir().glob("armed-*.json")):
        was = _read(path)
        if was is not None and isinstance(was.get("rig"), str):
            found.append((path, was))
    return found


def armed() -> list[dict[str, Any]]:
    """The armed markers whose process was judged running (a bench that may energise its rig now), each with
    ``alive``: how that was judged."""
    return [{**was, "alive": how} for path, was in _markers() for alive, how in [_alive(was, path)] if alive]


def _last_sign(where: str) -> str:
    """When the dead process's files (its run file; a manual session's log and its readings) last changed: the latch
    is stamped when it is found, possibly days later (an outside tester asked when the process died); '' when there
    is none."""
    name = where.removeprefix("manual session ")
    files = [Path(name)]
    if name != where:  # a session's readings go to <log>.h5 (or <log>-N.h5) between its commands' log lines
        files += Path(name).parent.glob(f"{glob.escape(Path(name).stem)}*.h5")
    times = []
    for f in files:
        with contextlib.suppress(OSError, ValueError):
            times.append(f.stat().st_mtime)
    if not times:
        return ""
    changed = max(times)
    return f" (its file last written {datetime.fromtimestamp(changed).astimezone().isoformat(timespec='seconds')})"


def _dead_markers_latch() -> dict[str, dict[str, Any]]:
    """Turn each armed marker whose process is gone into a latch of its rig (a latch already there is kept: the
    history says what else was found). Returns those that could not be written (a state folder this user may only
    read): latched all the same, for this look."""
    unwritten: dict[str, dict[str, Any]] = {}
    for path, was in _markers():
        if _alive(was, path)[0]:
            continue
        rig_name, where = was["rig"], str(was.get("where") or "?")
        fault = (f"the bench process (pid {was.get('pid')}, armed {was.get('at')}) ended without its shutdown "
                 f"(killed?) during {where}{_last_sign(where)}: zero neither commanded nor verified by the host"
                 if not was.get("paused") else
                 f"the bench process (pid {was.get('pid')}, armed {was.get('at')}) ended without its shutdown "
                 f"(killed?) while paused during {where}{_last_sign(where)}: the pause had verified it ("
                 f"{was['paused']}), nothing since")
        drive = None
        if isinstance(was.get("drive"), str):
            drive = Drive(was["drive"], frozenset(str(i) for i in was.get("drive_ids") or []))
        try:
            if _own(rig_name):
                _history(f"found dead\t{rig_name}\t{fault}\t(already latched: that latch kept)")
            else:
                latch(rig_name, fault, where, drive)
            path.unlink(missing_ok=True)
        except OSError as exc:
            record: dict[str, Any] = {"rig": rig_name, "fault": f"{fault} (not written to {state_dir()}: "
                                      f"{exc.strerror or exc})", "where": where, "at": was.get("at") or "?"}
            if drive is not None:
                record["drive"], record["drive_ids"] = drive.text, sorted(drive.ids)
            if not _own(rig_name):
                unwritten.setdefault(rig_name, record)
    return unwritten


def _own(rig_name: str) -> list[dict[str, Any]]:
    """Rig ``rig_name``'s own latches: its file (an unreadable one counts), then an older-form file that is its own
    or unreadable (names that clean up alike share it)."""
    found = []
    path = latch_path(rig_name)
    if path.exists():
        data = _read(path)
        found.append(data if data is not None else
                     {"rig": rig_name, "fault": f"latch file {path} unreadable", "where": "?", "at": "?"})
    old = _legacy(rig_name)
    if old is not None and (old.get("unreadable") or not found):
        found.append(old)
    return found


def _holding(rig_name: str, drive: Drive | None) -> list[dict[str, Any]]:
    """Every latch that holds rig ``rig_name``: its own first, then those of other rigs on ``drive`` (a bench that
    died energised latched first)."""
    unwritten = _dead_markers_latch()
    found = _own(rig_name) or ([unwritten[rig_name]] if rig_name in unwritten else [])
    if drive is not None:
        found += [was for name, was in all_latched().items() if name != rig_name and _on(was, drive)]
    return found


def holding(rig_name: str, drive: Drive | None = None) -> list[dict[str, Any]]:
    """Every latch that holds rig ``rig_name`` (its own first, then those of other rigs on ``drive``)."""
    return _holding(rig_name, drive)


def latch_key(was: dict[str, Any]) -> str:
    """One latch as a key (its rig, when it latched, its fault): the same key is the same latch, not a later one."""
    return json.dumps([was.get("rig"), was.get("at"), was.get("fault")])


def _changed(rig_name: str, found: list[dict[str, Any]], seen: Collection[str]) -> None:
    """LatchedError (one line) if a latch in ``found`` is not one of those ``seen`` (by :func:`latch_key`)."""
    new = next((was for was in found if latch_key(was) not in seen), None)
    if new is None:
        return
    name = new["rig"] if isinstance(new.get("rig"), str) else rig_name
    under = "" if name == rig_name else f" (under rig {name}, on its amplifier drive)"
    raise LatchedError(f"rig {rig_name}: latched again{under} at {new.get('at')} since the resume was planned "
                       f"({new.get('fault')}; in {new.get('where')}): its --why reset only the latch seen then — "
                       f"check the rig, then bench interlock reset {shlex.quote(name)} --why '…', or resume again")


def refuse_if_changed(rig_name: str, drive: Drive | None, seen: Collection[str]) -> None:
    """LatchedError (one line) while a latch holds rig ``rig_name`` (or its ``drive``) that is none of those
    ``seen`` when a resume's reset was planned (:func:`latch_key`): that reset is not this latch's."""
    _changed(rig_name, _holding(rig_name, drive), seen)


def latched(rig_name: str, drive: Drive | None = None) -> dict[str, Any] | None:
    """The latch of rig ``rig_name`` (fault, where, at), or else a latch of any rig on the same amplifier drive
    ``drive`` (its ``rig`` names the rig it was latched under), or None. An unreadable latch file counts as
    latched."""
    found = _holding(rig_name, drive)
    return found[0] if found else None


def all_latched() -> dict[str, dict[str, Any]]:
    """Every latch in the state folder, by exact rig name (as its file records it; the file name if it cannot
    be read); a bench that died energised latched first."""
    unwritten = _dead_markers_latch()
    found: dict[str, dict[str, Any]] = {}
    for path in sorted(state_dir().glob("interlock-*.json")):
        data = _read(path)
        if data is None or not isinstance(data.get("rig"), str):
            name = path.stem.removeprefix("interlock-")
            data = {"rig": name, "fault": f"latch file {path} unreadable", "where": "?", "at": "?"}
        found.setdefault(data["rig"], data)
    for name, was in unwritten.items():
        found.setdefault(name, was)
    return found


def reset(rig_name: str, by: str, why: str, drive: Drive | None = None,
          seen: Collection[str] | None = None) -> dict[str, Any] | None:
    """Reset every latch that holds ``rig_name`` (its own, and those of other rigs on ``drive``: the operator
    vouches for the hardware) — an explicit act: ``by`` and ``why`` required, each reset recorded in the history.
    Returns the first latch reset, or None if nothing was latched. An unreadable older-form latch file is left
    (it may be another rig's whose name cleans up alike): it still latches, its fault says to remove it by hand.
    ``seen``: the latches (:func:`latch_key`) the operator's reset was given for; LatchedError, nothing reset, if
    another holds the rig now."""
    if not by.strip() or not why.strip():
        raise ValueError("resetting the interlock needs who (--operator) and why (--why)")
    found = _holding(rig_name, drive)
    if seen is not None:
        _changed(rig_name, found, seen)
    for was in found:
        if was.get("unreadable"):  # the older form, whose name other rigs may share: not this command's to remove
            raise ValueError(f"rig {rig_name}: latch file {was['unreadable']} is unreadable and may be another rig's "
                             "(the older form: names that clean up alike share it): check the rigs, then remove "
                             "it by hand")
    for was in found:
        name = was["rig"] if isinstance(was.get("rig"), str) else rig_name
        latch_path(name).unlink(missing_ok=True)
        old = _read(_legacy_path(name)) if _legacy_path(name).exists() else None
        if old is not None and old.get("rig") == name:  # only a readable one of this very rig
            _legacy_path(name).unlink(missing_ok=True)
        same = drive.text if drive else "?"
        via = "" if name == rig_name else f" (latched under rig {name}, the same amplifier drive {same})"
        _history(f"reset\t{name}\tby {by}: {why}{via}\t(was: {was.get('fault')} in {was.get('where')})")
    return found[0] if found else None


def refuse_if_latched(rig_name: str, drive: Drive | None = None) -> None:
    """LatchedError (one line) while rig ``rig_name``, or another rig on its amplifier drive path, is latched."""
    was = latched(rig_name, drive)
    if was is None:
        return
    name = was["rig"] if isinstance(was.get("rig"), str) else rig_name
    who = f"rig {rig_name}:" if name == rig_name else f"rig {rig_name}: its amplifier drive " \
        f"({drive.text if drive else '?'}) is latched under rig {name};"
    raise LatchedError(f"{who} interlock latched at {was.get('at')} ({was.get('fault')}; in "
                       f"{was.get('where')}): nothing energises it until an operator resets it — "
                       f"bench interlock reset {shlex.quote(name)} --why '…', or bench run --resume RUN.h5 "
                       "--why '…'")
