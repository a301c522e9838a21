"""Transports for simulated instruments, with fault injection.

* :class:`PtyDevice` — one pty pair: the simulated instrument reads and writes the master side, the
  driver opens the slave's device path (``/dev/pts/N``) exactly as it would open ``/dev/ttyUSB0``.
* :class:`PtyBridge` — two pty pairs relayed back to back (the in-Python ``socat pty pty``), for servers
  that open a device path themselves (pymodbus' RTU server).
* :class:`SocketRelay` — a loopback TCP relay (asyncio) in front of a socket server (pymodbus' Modbus TCP
  or RTU-over-TCP server): the driver connects to the relay.

All three apply the same :class:`Faults` to what the instrument sends: extra latency, silence (timeouts),
garbled bytes, and a dropped link. A fault can be switched at once or armed for a time on the rig clock or
after a number of replies (:meth:`Faults.schedule`); ``Faults.injected`` counts the replies it affected.

:class:`Line` is the wire itself: a half-duplex serial line at a baud rate that every transaction on it
occupies for its character times, inter-frame gaps and the device's turnaround. On the wall clock those
durations are slept; on a virtual clock they advance it, so a virtual run takes the time a real one would.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import os
import select
import socket
import struct
import threading
import time
import tty
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from bench.core.clock import Clock, VirtualClock

SWITCHES = ("latency", "mute", "garble_next", "garble_index", "drop", "drop_reset", "wire_baud", "mutate")


@dataclass
class _Armed:
    """Switch settings waiting for their moment (one of the two conditions)."""

    switches: dict[str, object]
    at_time: float | None = None
    at_reply: int | None = None


@dataclass
class Faults:
    """Fault-injection switches of one simulated link (set from tests or ``bench sim serve``).

    Switches may be flipped at any time from any thread; :meth:`schedule` arms them for later. Counters:
    ``replies`` (replies the instrument produced), ``injected`` (replies or connections a fault acted on)
    and ``counts`` (the same by fault: ``latency``, ``mute``, ``garble``, ``drop``); for :class:`TwinTimer`,
    ``withheld`` (replies that never go on the wire: mute, a mutation to nothing, a request the instrument itself
    leaves unanswered: :meth:`unanswered`), ``altered`` (replies sent garbled
    or mutated: the driver may reject one and wait on; ``altered_at``: ``time.monotonic()`` of the last),
    ``delayed`` (replies held back by ``latency``) and ``last_latency`` (how long the last of them was held).
    """

    latency: float = 0.0  # s added before every reply (wall time)
    mute: bool = False  # swallow replies: the driver times out
    garble_next: int = 0  # corrupt this many following replies (one byte flipped per reply)
    garble_index: int | None = None  # which byte to flip (negative: from the end); None: a random one
    drop: bool = False  # close the link: the port reports a lost device
    drop_reset: bool = False  # sockets: drop with a TCP reset (a rebooted gateway), not an orderly close
    wire_baud: float | None = None  # emulate the wire time of request + reply at this baud rate (8N1)
    mutate: Callable[[bytes], bytes] | None = None  # rewrite every reply (fuzzing the drivers): b"" sends nothing
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    clock: Callable[[], float] | None = None  # the rig clock, for schedule(at_time=...)
    replies: int = field(default=0, init=False)
    injected: int = field(default=0, init=False)
    withheld: int = field(default=0, init=False)
    altered: int = field(default=0, init=False)
    altered_at: float = field(default=0.0, init=False)
    delayed: int = field(default=0, init=False)
    last_latency: float = field(default=0.0, init=False)
    counts: Counter[str] = field(default_factory=Counter, init=False)
    _armed: list[_Armed] = field(default_factory=list, init=False, repr=False)
    _lock: threading.RLock = field(default_factory=threading.RLock, init=False, repr=False, compare=False)  # re-entrant

    def schedule(self, *, at_time: float | None = None, after_replies: int | None = None,
                 **switches: object) -> None:
        """Arm ``switches`` (e.g. ``mute=True``) for when the rig clock reads ``at_time`` [s] (checked every few
        ms and at each reply), or to take effect on the reply after the next ``after_replies`` ones (0: the very
        next reply). Exactly one condition; several schedules may be pending."""
        if (at_time is None) == (after_replies is None):
            raise ValueError("schedule needs exactly one of at_time, after_replies")
        if unknown := set(switches) - set(SWITCHES):
            raise TypeError(f"unknown fault switch(es) {sorted(unknown)}; known: {', '.join(SWITCHES)}")
        if not switches:
            raise ValueError("schedule needs at least one switch")
        if at_time is not None and self.clock is None:
            raise ValueError("schedule(at_time=...) needs a clock (SimRig sets it to the rig clock)")
        if after_replies is not None and after_replies < 0:
            raise ValueError(f"after_replies must be >= 0, got {after_replies}")
        with self._lock:
            at_reply = None if after_replies is None else self.replies + after_replies
            self._armed.append(_Armed(dict(switches), at_time, at_reply))

    @property
    def pending(self) -> int:
        """Number of scheduled switch sets not yet applied."""
        with self._lock:
            return len(self._armed)

    def reset(self) -> None:
        """Clear every switch and schedule (counters are kept)."""
        with self._lock:
            self._armed.clear()
            self.latency, self.mute, self.garble_next, self.garble_index = 0.0, False, 0, None
            self.drop, self.drop_reset, self.wire_baud, self.mutate = False, False, None, None

    def tick(self, replying: bool = False) -> None:
        """Apply scheduled switches whose moment has come. Transports call this while idle (time schedules)
        and with ``replying`` as each reply passes (reply-count schedules too, so they hit that reply)."""
        with self._lock:
            if not self._armed:
                return
            timed = [a for a in self._armed if a.at_time is not None]
            now = self.clock() if timed and self.clock is not None else None
            due = [a for a in self._armed
                   if (a.at_time is not None and now is not None and now >= a.at_time)
                   or (replying and a.at_reply is not None and self.replies >= a.at_reply)]
            for a in due:
                self._armed.remove(a)
                for k, v in a.switches.items():
                    setattr(self, k, v)

    def unanswered(self) -> None:
        """The instrument answered a request with nothing (as the device does: not a fault, not in ``counts``)."""
        with self._lock:
            self.withheld += 1

    def note(self, *kinds: str) -> None:
        """Count one reply / connection affected by the fault(s) ``kinds``."""
        with self._lock:
            self.injected += 1
            self.counts.update(kinds)

    def process(self, reply: bytes, request_len: int = 0) -> tuple[bytes | None, float]:
        """What goes on the wire for ``reply`` (None: nothing) and the wall-time delay [s] before it."""
        if not reply:
            return None, 0.0
        with self._lock:
            self.tick(replying=True)
            self.replies += 1
            if self.mute:
                self.note("mute")
                self.withheld += 1
                return None, 0.0
            kinds = []
            if self.garble_next > 0:
                self.garble_next -= 1
                buf = bytearray(reply)
                n = len(buf)
                i = int(self.rng.integers(0, n)) if self.garble_index is None else self.garble_index % n
                buf[i] ^= 0x5A
                reply = bytes(buf)
                kinds.append("garble")
            if self.mutate is not None:
                reply = self.mutate(reply)
                kinds.append("mutate")
                if not reply:
                    self.note(*kinds)
                    self.withheld += 1
                    return None, 0.0
            if kinds:
                self.altered += 1
                self.altered_at = time.monotonic()
            delay = self.latency
            if delay > 0:
                kinds.append("latency")
                self.delayed += 1
                self.last_latency = delay
            if kinds:
                self.note(*kinds)
            if self.wire_baud:
                delay += 10.0 * (request_len + len(reply)) / self.wire_baud
            return reply, delay

    def apply(self, reply: bytes) -> bytes | None:
        """What goes on the wire for ``reply`` (None: nothing); the delay is the caller's business."""
        return self.process(reply)[0]


TWIN_STALL_S = 30.0  # virtual time: wall seconds before giving up on a twin that neither answers nor withholds


class TwinTimer:
    """How long a driver waits for a twin's reply in a virtual-time run (a :class:`drivers.deadline.ReplyTimer`).

    In virtual time the host's speed is no part of the simulation: a twin thread starved of CPU answers late, and
    that must never read as a silent instrument. So a wait is decided by what the twin did with the request, as
    its :class:`Faults` count it from the moment the request went out (:meth:`sending`):

    * it withheld the reply (``mute``, a mutation to nothing, a pty twin that answered with nothing), or held it
      back by a ``latency`` at least as long as the timeout: the wait expires at once, and the rig clock moves on
      to where the timeout would have ended it — the instrument stayed silent for the timeout, in rig time;
    * it sent the reply garbled or mutated: the driver may reject it and wait on for a reply that never comes,
      so this deliberate fault is judged as on hardware, by the timeout on the wall clock — counted from the
      wait's start, or from when the twin sent the reply if that is later (a late twin does not eat into it);
    * otherwise (a ``latency`` shorter than the timeout included) the reply is on its way, however slowly: the
      wait lasts until it comes, with ``stall`` s of wall time only as a guard against a twin that hangs, or a
      Modbus server that ignores a request behind a transport that cannot see it (the message says which).

    A silent twin is told apart from a slow host by the twin itself, not by a stopwatch: scaling the wall-clock
    timeouts up in virtual runs would still let a loaded enough host decide, and make each deliberate silence cost
    that long. ``bound`` (for the blocking calls a link cannot slice: a port write, a connect) is the guard too.
    """

    def __init__(self, faults: Faults, clock: VirtualClock, stall: float = TWIN_STALL_S,
                 waiting: Callable[[], None] | None = None) -> None:
        self.faults = faults
        self.clock = clock
        self.stall = stall
        self.waiting = waiting  # told before each blocking read of a wait (a twin that sends on demand: the T7's)
        self.mark = self._counts()

    def _counts(self) -> tuple[int, int, int]:
        f = self.faults
        return f.withheld, f.altered, f.delayed

    def sending(self) -> None:
        """A request is about to go out: what the twin does from here is done to its reply."""
        self.mark = self._counts()

    def start(self, timeout: float) -> TwinDeadline:
        """A wait of ``timeout`` s (rig time) for the reply to the request last sent."""
        return TwinDeadline(self, timeout)

    def bound(self, timeout: float) -> float:
        """The guard (never less than ``timeout``)."""
        return max(timeout, self.stall)


class TwinDeadline:
    """One wait of a :class:`TwinTimer` (``timeout`` ≤ 0: a look, expired at once)."""

    def __init__(self, timer: TwinTimer, timeout: float) -> None:
        self.faults, self.clock, self.stall = timer.faults, timer.clock, timer.stall
        self.waiting = timer.waiting
        self.timeout = timeout
        self.withheld, self.altered, self.delayed = timer.mark
        self.rig_end = self.clock.now() + timeout
        now = time.monotonic()
        self.wall_end = now + timeout
        self.guard_end = now + max(timeout, timer.stall)
        self.detail = ""

    def _silent(self) -> bool:
        """The reply will not come within the timeout: the twin withheld it or holds it back that long."""
        f = self.faults
        return f.withheld > self.withheld or (f.delayed > self.delayed and f.last_latency >= self.timeout)

    def expired(self) -> bool:
        """Whether to give up: at once on a silent twin, on the wall clock for an altered reply, else at the guard."""
        if self.timeout <= 0:
            return True
        if self._silent():
            self.clock.advance_to(self.rig_end)
            return True
        now = time.monotonic()
        if self.faults.altered > self.altered:
            return now >= self._altered_end()
        if now >= self.guard_end:
            self.detail = (f" (the simulated instrument neither answered nor withheld its reply for {self.stall:g} s "
                           "of wall time)")
            return True
        return False

    def left(self) -> float:
        """Wall seconds a blocking read may last before :meth:`expired` is asked again; the driver is about to
        block, so the timer's ``waiting`` callback (if any) is told first: a twin that sends on demand sends now."""
        if self.timeout <= 0 or self._silent():
            return 0.0
        if self.waiting is not None:
            self.waiting()
        end = self._altered_end() if self.faults.altered > self.altered else self.guard_end
        return max(end - time.monotonic(), 0.0)

    def _altered_end(self) -> float:
        """Wall-clock end of the wait for an altered reply: its timeout, from the start or from its sending."""
        return max(self.wall_end, self.faults.altered_at + self.timeout)


SPIN_S = 0.3e-3  # the last part of a wall-clock wire wait is spent yielding, not sleeping (see Line._until)


class Line:
    """A half-duplex serial wire (8N1: 10 bits per character) shared by everything on it.

    ``gap_chars``: silence that ends a frame (Modbus RTU: 3.5 characters, at least 1.75 ms above 19200 Bd —
    Modbus over Serial Line v1.02 §2.5.1.1); the device sees a request only after it, and the next frame
    may start only after it. ``baud`` None: no wire time at all (the old pty behaviour).
    """

    def __init__(self, clock: Clock, baud: float | None, *, gap_chars: float = 0.0, turnaround: float = 0.0,
                 bits_per_char: int = 10) -> None:
        self.clock = clock
        self.baud = baud
        self.bits_per_char = bits_per_char
        self.turnaround = turnaround
        self.gap = 0.0 if not baud else gap_chars * self.char_time
        if baud and gap_chars and baud > 19200:
            self.gap = max(self.gap, 1.75e-3) if gap_chars >= 3.5 else max(self.gap, 0.75e-3)
        self._free = 0.0  # line time at which the wire is next free
        self.lock = threading.RLock()  # one transaction on the wire at a time
        # wall clock: time a byte spends crossing the transport that stands in for the wire (a pty: one thread
        # wake-up), which the wire model must not add on top of its own time — see :func:`pty_hop_latency`
        self.hop = 0.0

    @property
    def char_time(self) -> float:
        """Seconds per character."""
        return self.bits_per_char / self.baud if self.baud else 0.0

    def frame_time(self, nbytes: int) -> float:
        """Seconds a frame of ``nbytes`` occupies the wire (without gaps)."""
        return nbytes * self.char_time

    def _until(self, t: float) -> None:
        """Wait until line time ``t``. On the wall clock the last ``SPIN_S`` are spent yielding instead of
        sleeping: a sleep overshoots by ~0.1 ms (timer slack and wake-up), which would add to every frame."""
        clock = self.clock
        if clock.virtual:
            clock.wait_until(t)
            return
        dt = t - clock.now()
        if dt > SPIN_S:
            time.sleep(dt - SPIN_S)
        while clock.now() < t:
            time.sleep(0)  # releases the GIL: other threads run while this one waits out the last fraction

    def request(self, nbytes: int) -> float:
        """The master's ``nbytes`` travel (from now, or when the wire frees); returns when the device has
        them and has seen the end-of-frame gap. Returns the line time of that moment."""
        if not self.baud:
            return self.clock.now()
        with self.lock:
            start = max(self.clock.now() - self.hop, self._free)  # the bytes left the host a hop ago
            end = start + self.frame_time(nbytes) + self.gap
            self._free = end
        self._until(end)
        return end

    def ready(self, turnaround: float | None = None) -> None:
        """The device is about to answer the request just received: wait until its reply may start, its turnaround
        after the wire was last busy (the request's end). A twin that reads its instrument after this puts into the
        reply what the device holds as it starts sending it — the instant a host stamps the reading with (the
        reply's arrival less its wire time), not the turnaround before."""
        if not self.baud:
            return
        with self.lock:
            t = self._free + (self.turnaround if turnaround is None else turnaround)
        self._until(t)

    def reply(self, nbytes: int, turnaround: float | None = None) -> None:
        """The device turns around and sends ``nbytes``; returns when the last byte has arrived.

        The first byte leaves ``turnaround`` after the wire was last busy (the request's end), or when the
        simulator is ready if that is later: the twin's own processing is the device's turnaround, not extra
        time on top of it."""
        if not self.baud:
            return
        with self.lock:
            t_turn = self.turnaround if turnaround is None else turnaround
            start = max(self.clock.now(), self._free + t_turn)
            end = start + self.frame_time(nbytes)
            self._free = end + self.gap
        self._until(end - self.hop)  # the last byte reaches the host a hop after it is written

    def crosses_pty(self) -> None:
        """This line's bytes cross a pty (wall clock, wire time on): take the pty's hop out of the wire time."""
        if self.baud and not self.clock.virtual:
            self.hop = pty_hop_latency()

    def silent(self, wait: float) -> None:
        """Nobody answers: the wire stays idle for ``wait`` s (e.g. a gateway's response timeout)."""
        self._until(self.clock.now() + wait)


HOP_SAMPLES = 30


@functools.cache
def pty_hop_latency() -> float:
    """A lower bound of the time from one thread writing a pty to another thread blocked on it waking with
    the bytes [s] (the minimum of ``HOP_SAMPLES`` measurements, taken once per process).

    A twin sees a request only after this hop and its reply reaches the host only after it again; a real wire
    has no such hop (the UART starts shifting at the write). Taking the *minimum* out of the emulated wire
    time keeps the twin from being faster than the wire model on a quiet machine and makes it no kinder on a
    busy one (the actual hop is then longer)."""
    master, slave, _ = _open_raw_pty()
    woke: list[float] = []
    ready, done = threading.Event(), threading.Event()

    def reader() -> None:
        for _ in range(HOP_SAMPLES):
            ready.set()
            while not done.is_set() and not select.select([master], [], [], 0.01)[0]:
                pass
            if done.is_set():
                return
            woke.append(time.perf_counter())
            os.read(master, 64)

    thread = threading.Thread(target=reader, daemon=True)
    sent: list[float] = []
    try:
        thread.start()
        for _ in range(HOP_SAMPLES):
            ready.wait(1.0)
            ready.clear()
            time.sleep(2e-4)  # let the reader block in select
            sent.append(time.perf_counter())
            os.write(slave, b"x")
            while len(woke) < len(sent) and thread.is_alive():
                time.sleep(1e-4)
    finally:
        # the reader ends before its pty closes: an exception here (a stop signal while the rig starts) must not
        # leave it selecting on a closed descriptor (a traceback from its thread on the way out)
        done.set()
        if thread.is_alive():
            thread.join(1.0)
        for fd in (master, slave):
            with contextlib.suppress(OSError):
                os.close(fd)
    hops = [w - t for w, t in zip(woke, sent, strict=False) if w > t]
    return min(hops) if hops else 0.0


def _open_raw_pty() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


class PtyDevice:
    """Serve a byte-stream instrument on a pty: ``handler(data) -> reply bytes`` per chunk received.

    The handler keeps its own framing state (it may get partial or several frames per call). Bytes it answers
    with nothing (noise, a framing or checksum error, another drive's telegram, a command cut short) leave it
    waiting for more: :meth:`Faults.unanswered` says so — a driver writes each request whole, and a pty hands a
    write that small to the reader in one piece, so the request it is waiting on will get no reply. ``drop``
    closes the pty for good, like an unplugged USB adapter: the device path disappears.
    """

    def __init__(self, handler: Callable[[bytes], bytes], name: str, faults: Faults | None = None,
                 line: Line | None = None) -> None:
        """``line``: the wire's timing for request and reply (None: the handler times itself, or no wire)."""
        self.handler = handler
        self.name = name
        self.faults = faults or Faults()
        self.line = line
        if line is not None:
            line.crosses_pty()
        self._master, self._slave, self.path = _open_raw_pty()
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()  # stop() wakes the serving thread's select at once (closed by stop)
        self._thread = threading.Thread(target=self._run, name=f"sim-{name}", daemon=True)
        self.error: BaseException | None = None

    def start(self) -> PtyDevice:
        """Start serving in a background thread."""
        self._thread.start()
        return self

    def _run(self) -> None:
        faults = self.faults
        try:
            while not self._stop.is_set():
                faults.tick()
                if faults.drop:
                    faults.note("drop")
                    break
                ready, _, _ = select.select([self._master, self._wake_r], [], [], 0.01)
                if self._master not in ready:
                    continue
                try:
                    data = os.read(self._master, 65536)
                except OSError:
                    break
                line = self.line
                if line is not None:
                    line.request(len(data))
                    line.ready()  # the reply reads the instrument as it starts, after the turnaround
                reply = self.handler(data)
                if not reply:
                    faults.unanswered()
                if reply and line is not None:
                    line.reply(len(reply))
                sent, delay = faults.process(reply, len(data))
                if sent:
                    if delay:
                        time.sleep(delay)
                    os.write(self._master, sent)
        except BaseException as exc:  # the simulator must not die silently
            self.error = exc
        finally:
            self._close_fds()

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1

    @property
    def alive(self) -> bool:
        """Whether the serving thread still runs."""
        return self._thread.is_alive()

    def stop(self) -> None:
        """Stop serving and close the pty (the serving thread is woken, not left to its next 10-ms poll)."""
        self._stop.set()
        if self._wake_w != -1:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"\0")
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        elif self._master != -1:
            self._close_fds()
        if not self._thread.is_alive():  # nothing selects on the pipe any more
            for fd in (self._wake_r, self._wake_w):
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._wake_r = self._wake_w = -1


class PtyBridge:
    """Two pty pairs relayed back to back: ``server_path`` for the simulator, ``client_path`` for the driver.

    Faults apply to bytes travelling server → client; ``drop`` closes the client side for good.
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
        faults, request_len = self.faults, 0
        try:
            while not self._stop.is_set():
                faults.tick()
                if faults.drop:
                    faults.note("drop")
                    break
                ready, _, _ = select.select([self._sm, self._cm], [], [], 0.01)
                for fd in ready:
                    try:
                        data = os.read(fd, 65536)
                    except OSError:
                        return
                    if fd == self._cm:
                        request_len = len(data)
                        os.write(self._sm, data)
                        continue
                    out, delay = faults.process(data, request_len)
                    if out:
                        if delay:
                            time.sleep(delay)
                        os.write(self._cm, out)
        finally:
            for fd in (self._cm, self._cs) if faults.drop else ():
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


class SocketRelay:
    """Loopback TCP relay in front of a socket server, run in an asyncio loop; faults act on server → client.

    ``framing``: ``"mbap"`` cuts the server's stream into Modbus TCP ADUs (so faults act per reply whatever
    the segmentation); ``"stream"`` treats each chunk read as one reply (RTU over TCP). ``drop`` closes every
    open connection (as a server that died: FIN; with ``drop_reset``: RST) and the listening socket (new
    connections are refused) until it is cleared, then the relay listens on the same port again.

    ``local`` (``"mbap"`` only): a device's own answer to a request, given the whole ADU, or None to pass it on,
    computed at once (no await: the request read, answered and its reply written in one step). It is asked only
    for a read that holds exactly one whole ADU while no request passed on is unanswered (so replies keep the
    requests' order); its reply goes through the same faults as the server's. A twin answers its busiest request
    here (the T7's MBFB packets) and saves the hop to its server and back.
    """

    def __init__(self, name: str, upstream: tuple[str, int], faults: Faults | None = None,
                 framing: Literal["mbap", "stream"] = "stream", poll: float = 0.005,
                 local: Callable[[bytes], bytes | None] | None = None) -> None:
        self.name = name
        self.upstream = upstream
        self.faults = faults or Faults()
        self.framing = framing
        self.local = local if framing == "mbap" else None
        self.host, self.port = "127.0.0.1", 0
        self._poll = poll
        self._server: asyncio.Server | None = None
        self._watch: asyncio.Handle | asyncio.Task[None] | None = None  # the next look at the faults, or its action
        self._conns: set[tuple[asyncio.StreamWriter, asyncio.StreamWriter]] = set()

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) the driver connects to."""
        return self.host, self.port

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> SocketRelay:
        """Listen on ``host:port`` (0: ephemeral) and start watching the faults."""
        self.host = host
        self._server = await self._listen(host, port)
        self.port = self._server.sockets[0].getsockname()[1]
        self._watch = asyncio.get_running_loop().call_soon(self._watch_faults)
        return self

    async def close(self) -> None:
        """Stop listening and reset every connection."""
        watch = self._watch
        if watch is not None:
            watch.cancel()
            if isinstance(watch, asyncio.Task):
                with contextlib.suppress(asyncio.CancelledError):
                    await watch
        self._stop_listening()
        self._close_all()

    def _stop_listening(self) -> None:
        if self._server is not None:  # close() shuts the listening sockets at once; no wait_closed (3.12+
            self._server.close()  # waits there for open connections, and a drop may come from one of them)
            self._server = None

    def _close_all(self, reset: bool = True) -> None:
        conns, self._conns = self._conns, set()
        for cwriter, swriter in conns:
            _reset(swriter)
            if reset:
                _reset(cwriter)
            else:
                cwriter.close()

    def _watch_faults(self) -> None:
        """Every ``poll`` s: tick the faults' schedules; a drop (while listening) or its end (listening again) is
        acted on in a task, and the watch goes on after it. A timer callback while there is nothing to act on (a
        task sleeping between looks took a future and a second pass of the loop at every poll)."""
        faults = self.faults
        faults.tick()
        loop = asyncio.get_running_loop()
        if bool(faults.drop) == (self._server is not None):  # dropped while listening, or no longer dropped
            self._watch = loop.create_task(self._act_on_faults())
        else:
            self._watch = loop.call_later(self._poll, self._watch_faults)

    async def _act_on_faults(self) -> None:
        if self.faults.drop:
            await self._drop()
        else:
            with contextlib.suppress(OSError):  # port briefly taken: try again next poll
                self._server = await self._listen(self.host, self.port)
        self._watch = asyncio.get_running_loop().call_later(self._poll, self._watch_faults)

    async def _drop(self) -> None:
        """Stop listening first (no reconnection slips in), then close the open connections."""
        if self._server is None:
            return
        self._stop_listening()
        self._close_all(reset=self.faults.drop_reset)
        self.faults.note("drop")

    async def _listen(self, host: str, port: int) -> asyncio.Server:
        """``asyncio.start_server`` of :meth:`_handle`, with the clients' bytes read by a :class:`_Requests`."""
        loop = asyncio.get_running_loop()

        def protocol() -> asyncio.StreamReaderProtocol:
            return asyncio.StreamReaderProtocol(_Requests(loop=loop), self._handle, loop=loop)

        return await loop.create_server(protocol, host, port)

    async def _handle(self, creader: asyncio.StreamReader, cwriter: asyncio.StreamWriter) -> None:
        if self.faults.drop:  # accepted just before the listener closed
            if self.faults.drop_reset:
                _reset(cwriter)
            else:
                cwriter.close()
            return
        try:
            sreader, swriter = await asyncio.open_connection(*self.upstream)
        except OSError:
            _reset(cwriter)
            return
        pair = (cwriter, swriter)
        self._conns.add(pair)
        conn = _Conn()
        if self.local is not None and isinstance(creader, _Requests):
            creader.answer = functools.partial(self._answer_now, cwriter, conn)
        loop = asyncio.get_running_loop()
        tasks = [loop.create_task(self._requests(creader, swriter, cwriter, conn)),
                 loop.create_task(self._replies(sreader, cwriter, conn))]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in [*tasks, *([conn.later] if conn.later is not None else [])]:
                t.cancel()
            self._conns.discard(pair)
            for w in pair:
                w.close()

    async def _requests(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                        client: asyncio.StreamWriter, conn: _Conn) -> None:
        with contextlib.suppress(OSError):
            while data := await reader.read(65536):
                try:
                    if (later := conn.later) is not None and not await later:  # a local reply held back goes first
                        return
                    conn.last_request = len(data)
                    if self.local is not None and not conn.pending and len(data) >= 8 \
                            and len(data) == 6 + int.from_bytes(data[4:6], "big"):
                        reply = self.local(data)
                        if reply is not None:
                            if not await self._deliver(client, reply, len(data)):
                                return
                            continue
                    if self.local is not None:  # only a relay that answers locally needs the count
                        conn.pending += _adus(data)
                    writer.write(data)
                    await writer.drain()
                finally:
                    if isinstance(reader, _Requests):
                        reader.queued -= len(data)

    def _answer_now(self, writer: asyncio.StreamWriter, conn: _Conn, data: bytes) -> bool:
        """Answer the request in ``data`` as it arrives, if ``local`` answers it and its reply can go on the wire at
        once: no request passed on unanswered, no reply waiting in the socket, no latency, wire time, drop or
        schedule to wait on (those take :meth:`_requests`' path). False: not answered (nothing was done).

        A latency or wire time another thread switches on while the reply is made is this reply's too: the faults
        decide once (:meth:`Faults.process`, under their lock), and a delay they give holds the reply back in a
        task (``conn.later``) that the connection's next request waits behind."""
        f = self.faults
        if conn.pending or conn.later is not None or not 8 <= len(data) == 6 + int.from_bytes(data[4:6], "big") \
                or f.latency or f.wire_baud or f.drop or f._armed or writer.transport.get_write_buffer_size():
            return False
        reply = self.local(data) if self.local is not None else None
        if reply is None:
            return False
        conn.last_request = len(data)
        out, delay = f.process(reply, len(data))
        if f.drop:  # set by another thread meanwhile: as :meth:`_deliver`, the link goes before the reply
            asyncio.get_running_loop().create_task(self._drop())
        elif delay and out is not None:  # switched on since the check above: counted delayed, so sent late
            conn.later = later = asyncio.get_running_loop().create_task(self._send(writer, out, delay))
            later.add_done_callback(lambda t: setattr(conn, "later", None) if conn.later is t else None)
        elif out is not None:
            writer.write(out)
        return True

    async def _replies(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, conn: _Conn) -> None:
        with contextlib.suppress(OSError, asyncio.IncompleteReadError):
            while True:
                if self.framing == "mbap":
                    head = await reader.readexactly(6)
                    reply = head + await reader.readexactly(int.from_bytes(head[4:6], "big"))
                    conn.pending = max(conn.pending - 1, 0)  # (stays 0 on a relay without a local answer)
                else:
                    reply = await reader.read(65536)
                if not reply:
                    return
                if not await self._deliver(writer, reply, conn.last_request):
                    return

    async def _deliver(self, writer: asyncio.StreamWriter, reply: bytes, request_len: int) -> bool:
        """Put one reply on the client's wire through the faults; False once the link has been dropped."""
        out, delay = self.faults.process(reply, request_len)
        return await self._send(writer, out, delay)

    async def _send(self, writer: asyncio.StreamWriter, out: bytes | None, delay: float) -> bool:
        """Put a reply the faults have processed (``out``, None: nothing) on the wire after ``delay`` [s]; False
        once the link has been dropped."""
        if self.faults.drop:
            await self._drop()
            return False
        if out is None:
            return True
        if delay:
            await asyncio.sleep(delay)
        if self.faults.drop:  # set by this reply's schedule, or during the delay
            await self._drop()
            return False
        writer.write(out)
        if writer.transport.get_write_buffer_size():  # only a reply the socket did not take at once waits for it
            await writer.drain()
        return True


class _Requests(asyncio.StreamReader):
    """The client's side of a relayed connection. Once the relay sets ``answer`` (a relay with a ``local`` answer,
    :meth:`SocketRelay._answer_now`), bytes that arrive while nothing earlier waits in the relay's task are offered
    to it first, in the event loop's read callback: a request answered there costs no task hop, no future, no
    second pass of the loop. Bytes it does not take go to the task (:meth:`SocketRelay._requests`), and so do all
    that follow until the task has handled them (``queued``): the replies keep the requests' order."""

    answer: Callable[[bytes], bool] | None = None
    queued = 0  # bytes fed to the task and not yet handled by it

    def feed_data(self, data: bytes) -> None:  # type: ignore[override]  # the protocol feeds what it received: bytes
        if not self.queued and self.answer is not None and self.answer(data):
            return
        self.queued += len(data)
        super().feed_data(data)


@dataclass
class _Conn:
    """One relayed connection: the size of the last request read, and the requests passed on not yet answered
    (counted per MBAP ADU, a cut one included: it may be answered once the rest comes)."""

    last_request: int = 0
    pending: int = 0
    later: asyncio.Task[bool] | None = None  # a local reply held back by a latency switched on while it was made


def _adus(data: bytes) -> int:
    """Modbus TCP ADUs begun in ``data`` (a read may hold several, or a part of one)."""
    i = n = 0
    while i + 6 <= len(data):
        n += 1
        i += 6 + int.from_bytes(data[i + 4:i + 6], "big")
    return n + (0 < len(data) - i < 6)  # a header cut short


def _reset(writer: asyncio.StreamWriter) -> None:
    """Close a connection with a TCP reset (the peer sees the link die, not an orderly end)."""
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    writer.transport.abort()
