"""One process at a time per instrument: a run, a manual-control session or a device check claims every instrument
address of a real rig before it connects to any, and holds the claims until its instruments are closed.

Without it a second ``bench run`` on a rig that is running got as far as connecting to the T7 (whose connect stops
a stream) before a serial port refused it, and ``bench devices control`` could set a voltage on an output the run
believed was its own. A serial port is also opened exclusively by its driver; the claims add the TCP instruments
(T7, Modbus TCP) and refuse before anything is touched, naming the process that holds the instrument.

Claims are ``flock`` locks on one file per address in the temporary directory (``$BENCH_LOCK_DIR`` to change it),
so they cover every user of this machine and are released by the kernel when the holder ends, however it ends. They
do not see another computer on the same network: an instrument reached over TCP from two machines is not caught.
A simulated rig's twins belong to the process that starts them: nothing to claim. Where the platform has no
``flock`` (Windows) nothing is claimed either.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path

from bench.rig import RigConfig

LOCK_DIR_ENV = "BENCH_LOCK_DIR"


class RigInUseError(ValueError):
    """An instrument of the rig is held by another process (one line: the instrument, its address, the holder)."""


def lock_dir() -> Path:
    """Where the claims live (``$BENCH_LOCK_DIR``, made if missing, or the temporary directory: shared by every
    user). ValueError (one line naming the variable) when it cannot be made."""
    folder = Path(os.environ.get(LOCK_DIR_ENV) or tempfile.gettempdir())
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"{LOCK_DIR_ENV}={folder}: cannot make the folder of the instrument claims "
                         f"({exc.strerror or exc})") from None
    return folder


def _serial(port: str) -> str:
    """A serial port's address: a device path resolved (``/dev/serial/by-id/…`` → ``/dev/ttyUSB0``), a URL as is."""
    return port if "://" in port else f"serial:{os.path.realpath(port)}"


def addresses(rig: RigConfig, endpoints: dict[str, str] | None = None) -> dict[str, str]:
    """Role (or bus name) → the address of every instrument ``rig`` connects to (``endpoints`` override the file's
    ports, as :func:`~bench.runtime.instruments.build_instruments` takes them)."""
    ep = endpoints or {}
    out: dict[str, str] = {}
    if (d := rig.daq) is not None:
        out["daq"] = f"tcp://{d.host.lower()}:{d.port}" if "daq" not in ep else f"tcp://{ep['daq'].rsplit(':', 1)[0]}"
    buses = set()
    if (a := rig.amplifier) is not None and a.drive != "daq":
        buses.add(a.bus)
    if (c := rig.load_cell) is not None:
        buses.add(c.bus)
    for name in sorted(buses):
        port = ep.get(name, rig.buses[name].port)
        out[f"bus {name}"] = port.lower() if port.startswith("tcp://") else _serial(port)
    if (lz := rig.laser) is not None:
        out["laser"] = _serial(ep.get("laser", lz.port))
    if (m := rig.motor) is not None:
        out["motor"] = _serial(ep.get("motor", m.port))
    return out


def _holder(fd: int) -> str:
    """What the claim file says of its holder (``process PID (command)``), or a plain 'another process'."""
    with contextlib.suppress(OSError, UnicodeDecodeError):
        text = os.pread(fd, 512, 0).decode().strip()
        if text:
            return text
    return "another process"


def _claim(path: Path, refused: Callable[[str], ValueError], busy: Callable[[str], ValueError]) -> int:
    """An ``flock`` on the claim file ``path``, its holder written into it: the descriptor (closing it releases the
    claim). ``refused(why)`` for a claim file that cannot be used, ``busy(holder)`` for one another process holds."""
    import fcntl

    # O_NOFOLLOW: a link planted in a shared folder is not followed; O_NONBLOCK: nor does a planted FIFO block the
    # open; 0o666: any user may claim it next
    flags = os.O_NOFOLLOW | os.O_NONBLOCK
    try:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | flags, 0o666)
        except PermissionError:  # another user's claim file umask left read-only: a read lock still locks
            fd = os.open(path, os.O_RDONLY | flags)
    except OSError as exc:
        raise refused(exc.strerror or type(exc).__name__) from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise refused("not a regular file: remove it")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _holder(fd)
        os.close(fd)
        raise busy(holder) from None
    except OSError as exc:  # no locks on this filesystem (some network or FUSE mounts): $BENCH_LOCK_DIR
        os.close(fd)
        raise refused(f"{exc.strerror}; set {LOCK_DIR_ENV} to a local folder") from None
    with contextlib.suppress(OSError):  # who holds it, for the next one refused (a read-only file: unsaid)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"process {os.getpid()} ({' '.join(sys.argv[:3])[:200]})".encode(), 0)
    return fd


def _release(fd: int) -> None:
    with contextlib.suppress(OSError):
        os.ftruncate(fd, 0)
    os.close(fd)  # closing the descriptor releases the lock


@contextlib.contextmanager
def claimed(rig: RigConfig, endpoints: dict[str, str] | None = None) -> Iterator[None]:
    """Hold every instrument address of ``rig`` for the block; RigInUseError (nothing connected, nothing held) if
    another process holds one. A simulated rig claims nothing."""
    if rig.simulated or sys.platform == "win32":
        yield
        return
    held: list[int] = []
    by_address: dict[str, list[str]] = {}  # one claim per address (two buses on one gateway are one instrument)
    for role, address in addresses(rig, endpoints).items():
        by_address.setdefault(address, []).append(role)
    try:
        folder = lock_dir()
        for address, roles in sorted(by_address.items()):
            role = " and ".join(roles)
            name = hashlib.sha256(address.encode()).hexdigest()[:16]
            path = folder / f"dea-bench-instrument-{name}.lock"

            def refused(why: str, path: Path = path, role: str = role, address: str = address) -> ValueError:
                return RigInUseError(f"rig {rig.name}: cannot claim the {role} at {address} ({path}: {why})")

            def busy(holder: str, role: str = role, address: str = address) -> ValueError:
                return RigInUseError(f"rig {rig.name}: the {role} at {address} is in use by {holder}; one process "
                                     "at a time drives an instrument (stop that one first)")

            held.append(_claim(path, refused, busy))
        yield
    finally:
        for fd in held:
            _release(fd)


@contextlib.contextmanager
def campaign_claimed(previous: Path) -> Iterator[None]:
    """Hold the continuation of the campaign whose latest file is ``previous`` for the block (a resumed run, from
    before its file is made to its end): ValueError (one line) while another process resumes it. Without it two
    ``bench run --resume`` of one file started together both passed the "already resumed" check and forked the
    campaign. Simulated rigs too: the file is the campaign's, whatever drives it."""
    if sys.platform == "win32":
        yield
        return
    where = os.path.realpath(previous)
    path = lock_dir() / f"dea-bench-campaign-{hashlib.sha256(where.encode()).hexdigest()[:16]}.lock"

    def refused(why: str) -> ValueError:
        return ValueError(f"run file {previous}: cannot claim its campaign ({path}: {why})")

    def busy(holder: str) -> ValueError:
        return ValueError(f"run file {previous}: its campaign is being resumed by {holder}; one continuation at a "
                          "time")

    fd = _claim(path, refused, busy)
    try:
        yield
    finally:
        _release(fd)
