"""Pseudo-terminal transports for simulated serial instruments, with fault injection.

* :class:`PtyDevice` — one pty pair: the simulated instrument reads and writes the master side, the
  driver opens the slave's device path (``/dev/pts/N``) exactly as it would open ``/dev/ttyUSB0``.
* :class:`PtyBridge` — two pty pairs relayed back to back (the in-Python ``socat pty pty``), for servers
  that open a device path themselves (pymodbus' RTU server).

Both apply the same :class:`Faults` to what the instrument sends: extra latency, silence (timeouts),
garbled bytes, and a dropped connection (the master side is closed, the driver sees the port die).
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Faults:
    """Fault-injection switches of one simulated link (set from tests or ``bench sim serve``)."""

    latency: float = 0.0  # s added before every reply (wall time)
    mute: bool = False  # swallow replies: the driver times out
    garble_next: int = 0  # corrupt this many following replies (one byte flipped per reply)
    garble_index: int | None = None  # which byte to flip (negative: from the end); None: a random one
    drop: bool = False  # close the link: the port reports a lost device
    wire_baud: float | None = None  # emulate the wire time of request + reply at this baud rate (8N1)
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))

    def apply(self, reply: bytes) -> bytes | None:
        """Return what actually goes on the wire for ``reply`` (None: nothing)."""
        if self.mute or not reply:
            return None
        if self.garble_next > 0:
            self.garble_next -= 1
            buf = bytearray(reply)
            i = int(self.rng.integers(0, len(buf))) if self.garble_index is None else self.garble_index % len(buf)
            buf[i] ^= 0x5A
            return bytes(buf)
        return reply


def _open_raw_pty() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class PtyDevice:
    """Serve a byte-stream instrument on a pty: ``handler(data) -> reply bytes`` per chunk received.

    The handler keeps its own framing state (it may get partial or several frames per call).
    """

    def __init__(self, handler: Callable[[bytes], bytes], name: str, faults: Faults | None = None) -> None:
        self.handler = handler
        self.name = name
        self.faults = faults or Faults()
        self._master, self._slave, self.path = _open_raw_pty()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"sim-{name}", daemon=True)
        self.error: BaseException | None = None

    def start(self) -> PtyDevice:
        """Start serving in a background thread."""
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self.faults.drop:
                    break
                ready, _, _ = select.select([self._master], [], [], 0.01)
                if not ready:
                    continue
                try:
                    data = os.read(self._master, 65536)
                except OSError:
                    break
                reply = self.faults.apply(self.handler(data))
                if reply:
                    delay = self.faults.latency
                    if self.faults.wire_baud:
                        delay += 10.0 * (len(data) + len(reply)) / self.faults.wire_baud
                    if delay:
                        time.sleep(delay)
                    os.write(self._master, reply)
        except BaseException as exc:  # the simulator must not die silently
            self.error = exc
        finally:
            self._close_fds()

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1

    def stop(self) -> None:
        """Stop serving and close the pty."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        elif self._master != -1:
            self._close_fds()


class PtyBridge:
    """Two pty pairs relayed back to back: ``server_path`` for the simulator, ``client_path`` for the driver.

    Faults apply to bytes travelling server → client.
    """

    def __init__(self, name: str, faults: Faults | None = None) -> None:
        self.name = name
        self.faults = faults or Faults()
        self._sm, self._ss, self.server_path = _open_raw_pty()
        self._cm, self._cs, self.client_path = _open_raw_pty()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"bridge-{name}", daemon=True)

    def start(self) -> PtyBridge:
        """Start relaying."""
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            while not self._stop.is_set() and not self.faults.drop:
                ready, _, _ = select.select([self._sm, self._cm], [], [], 0.01)
                for fd in ready:
                    try:
                        data = os.read(fd, 65536)
                    except OSError:
                        return
                    if fd == self._cm:
                        os.write(self._sm, data)
                    else:
                        out = self.faults.apply(data)
                        if out:
                            if self.faults.latency:
                                time.sleep(self.faults.latency)
                            os.write(self._cm, out)
        finally:
            for fd in (self._cm, self._cs) if self.faults.drop else ():
                with contextlib.suppress(OSError):
                    os.close(fd)

    def stop(self) -> None:
        """Stop relaying and close all four descriptors."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        for fd in (self._sm, self._ss, self._cm, self._cs):
            with contextlib.suppress(OSError):
                os.close(fd)
