"""Simulated Keyence LK-G3000 / LK-G5000 controller speaking its RS-232C ASCII protocol on a pty.

Behaviour modelled: general vs communication mode (settings refused in general mode and vice versa with
the model's status-error code), the 8-character value format with over-range (``±FFFFFFF``) and invalid
(``XXXXXXXX``) values, 0.1-µm display quantisation, seeded Gaussian noise, the measuring range of the head,
data storage filled from the plant at the configured cycle up to a capacity, error replies to unknown,
malformed or mis-parameterised commands.

Written from the manual, not from :mod:`drivers.keyence` (no constant is shared). Sources: LK-G user manual
LK-G-M-NO5-E ch. 5 "RS-232C": p. 5-5 command/response/error format ("the main command or identifier that has
been received is added as a header"; error codes 00/01/20/21/22/88/99), p. 5-6 measurement-value format,
p. 5-24 output format. Marked [C]: taken from public drivers written against real units (DESY
cmstkmodlab ``devices/Keyence``; theion-batteries ``firm_keyence_rs232`` for the LK-G5000 codes and MS/MM/MA);
[assumed]: found in no source — chosen here and to be checked on a unit.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Literal

import numpy as np

from bench.core.clock import Clock
from bench.core.noise import LKG_AVERAGING, lkg_noise_mm
from bench.core.plant import Plant, PlantBlock

Model = Literal["LK-G3000", "LK-G5000"]
# Error codes: LK-G3000 from p. 5-5; LK-G5000 [C] theion Keyence_API.h (50 command … 62 parameter range).
ERR = {"LK-G3000": {"command": "00", "status": "01", "length": "20", "count": "21", "param": "22"},
       "LK-G5000": {"command": "50", "status": "51", "length": "60", "count": "61", "param": "62"}}
SAMPLING_US = (20, 50, 100, 200, 500, 1000)  # SW,CA codes 0..5 [C] DESY Keyence.cpp
STORAGE_CYCLES = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)  # SW,EB codes [assumed]; ratios: LKIF enum [V header]
STORAGE_CAPACITY: dict[Model, int] = {"LK-G3000": 65_536, "LK-G5000": 999_999}  # points per OUT [assumed]
OUTS: dict[Model, int] = {"LK-G3000": 2, "LK-G5000": 12}  # OUT numbers the controller accepts
MAX_AO_POINTS = 1000  # points per AO request [assumed]
TURNAROUND_S = 0.5e-3  # command received → first reply byte [assumed: no figure in the pages read]


def value_field(mm: float, range_mm: float = math.inf) -> str:
    """8-character measurement value (p. 5-6): sign + 7 characters with the point, right-aligned;
    ``±FFFFFFF`` beyond the range, ``XXXXXXXX`` no valid value (NaN). Four decimals (0.1 µm, LK-G152/H152)."""
    if not math.isfinite(mm):
        return "XXXXXXXX"
    sign = "-" if mm < 0 else "+"
    body = f"{abs(mm):07.4f}"
    if len(body) > 7 or abs(mm) > range_mm:
        return sign + "FFFFFFF"
    return sign + body


def value_fields(mm: np.ndarray, range_mm: float = math.inf) -> str:
    """Comma-separated value fields (:func:`value_field`) of many values, vectorised."""
    mm = np.asarray(mm, dtype=float)
    finite = np.isfinite(mm)
    a = np.zeros(mm.size, dtype=np.int64)
    a[finite] = np.round(np.abs(mm[finite]) * 1e4).astype(np.int64)
    out = np.empty((mm.size, 9), dtype=np.uint8)
    out[:, 8] = ord(",")
    out[:, 0] = np.where(mm < 0, ord("-"), ord("+"))
    for col, power in ((1, 100_000), (2, 10_000), (4, 1000), (5, 100), (6, 10), (7, 1)):
        out[:, col] = ord("0") + (a // power) % 10
    out[:, 3] = ord(".")
    over = finite & ((a >= 1_000_000) | (np.abs(mm) > range_mm))
    out[over, 1:8] = ord("F")
    out[~finite, 0:8] = ord("X")
    return out.tobytes()[:-1].decode("ascii")


@dataclass
class LaserHead:
    """Measuring geometry of the head: reading [mm] = offset + sign × 1000 × plant displacement [m]."""

    offset_mm: float = 0.0
    sign: float = 1.0
    range_mm: float = 40.0  # ± measuring range around the reference distance (LK-G152/LK-H152: ±40 mm)
    noise_mm: float = 0.0002  # rms (0.2 µm); a rig's twin sets it from the head and averaging (bench.core.noise)


class _RejectError(Exception):
    def __init__(self, kind: str) -> None:
        self.kind = kind


class KeyenceLKGSim:
    """Protocol handler of the simulated controller (feed it bytes; it returns the reply bytes)."""

    def __init__(self, plant: Plant, clock: Clock, *, model: Model = "LK-G3000", head: LaserHead | None = None,
                 capacity: int | None = None, seed: int = 1, outs: int = 1, head_model: str | None = None,
                 averaging: int = 64, noise: bool = True) -> None:
        """``outs``: OUTs with a head configured (others read ``XXXXXXXX``); ``capacity``: storage points per OUT
        (default: the model's, :data:`STORAGE_CAPACITY`); ``head_model`` (e.g. ``LK-G152``): the head's noise at
        ``averaging`` replaces ``head.noise_mm`` and follows the averaging setting (``SW,OC``); ``noise``: False
        for ideal readings."""
        self.plant = plant
        self.clock = clock
        self.model: Model = model
        self.head = head or LaserHead()
        self.capacity = capacity or STORAGE_CAPACITY[model]
        self.outs = outs
        self.panel_locked = False
        self.head_model, self.noise = head_model, noise
        self.averaging = averaging
        self._set_noise()
        self.rng = np.random.default_rng(seed)
        self.comm_mode = False
        self.program = 0
        self.sampling_code = 2  # 100 µs
        self.storage_cycle_code = 0
        self.storage_points = self.capacity
        self.storing = False
        self._store = np.empty(0)  # storage memory [mm] (NaN = invalid), allocated when storage starts
        self.n_stored = 0
        self._next_sample_t = 0.0
        # last (t, displacement) seen, for interpolation: from the start, the plant's present state (a storage
        # started before any block stores it as its first point, not the first block's value)
        self._prev: tuple[float, float] | None = (float(plant.last.t[-1]), float(plant.last.displacement[-1]))
        self._buf = b""
        self._lock = threading.Lock()
        self.fault_error_code: str | None = None  # answer every command with ER,<cmd>,<code> while set
        plant.listeners.append(self._on_block)

    def _set_noise(self) -> None:
        if self.head_model is not None:
            self.head.noise_mm = lkg_noise_mm(self.head_model, self.averaging) if self.noise else 0.0
        elif not self.noise:
            self.head.noise_mm = 0.0

    # ------------------------------------------------------------ plant side
    def _to_mm(self, disp_m: np.ndarray) -> np.ndarray:
        return self.head.offset_mm + self.head.sign * 1e3 * disp_m

    @property
    def storage_interval(self) -> float:
        """Seconds between stored points."""
        return SAMPLING_US[self.sampling_code] * STORAGE_CYCLES[self.storage_cycle_code] * 1e-6

    def _on_block(self, block: PlantBlock) -> None:
        with self._lock:
            if self._prev is None:
                self._prev = (float(block.t[0]) - self.plant.h, float(block.displacement[0]))
            if self.storing:
                t = np.concatenate([[self._prev[0]], block.t])
                u = np.concatenate([[self._prev[1]], block.displacement])
                dt = self.storage_interval
                n_room = self.storage_points - self.n_stored
                n_due = int(np.floor((t[-1] - self._next_sample_t) / dt + 1e-9)) + 1
                ts = self._next_sample_t + dt * np.arange(max(0, min(n_room, n_due)))
                if ts.size:
                    mm = self._to_mm(np.interp(ts, t, u)) + self.rng.normal(0.0, self.head.noise_mm, ts.size)
                    self._store[self.n_stored:self.n_stored + mm.size] = mm
                    self.n_stored += mm.size
                    self._next_sample_t = float(ts[-1]) + dt
                if self.n_stored >= self.storage_points:
                    self.storing = False
            self._prev = (float(block.t[-1]), float(block.displacement[-1]))

    def _value_field(self, mm: float) -> str:
        return value_field(round(mm, 4) if math.isfinite(mm) else mm, self.head.range_mm)

    def measure(self, out: int = 1) -> str:
        """Current reading of ``out`` as an 8-character field (no head on it: ``XXXXXXXX``)."""
        if out > self.outs:
            return self._value_field(math.nan)
        obs = self.plant.observe()
        mm = float(self._to_mm(obs.displacement)[0]) + float(self.rng.normal(0.0, self.head.noise_mm))
        return self._value_field(mm)

    # ------------------------------------------------------------ protocol side
    def __call__(self, data: bytes) -> bytes:
        """Feed received bytes; return the replies to every complete command."""
        self._buf += data
        out = b""
        while b"\r" in self._buf:
            line, self._buf = self._buf.split(b"\r", 1)
            out += self.reply(line) + b"\r"
        if len(self._buf) > 256:  # no CR in sight: a command-length error, as the controller does
            self._buf = b""
            out += f"ER,??,{ERR[self.model]['length']}\r".encode()
        return out

    def reply(self, line: bytes) -> bytes:
        """Reply (without CR) to one command line."""
        try:
            text = line.decode("ascii").strip()
        except UnicodeDecodeError:
            return f"ER,??,{ERR[self.model]['command']}".encode()
        fields = text.split(",")
        main = fields[0].upper()
        if self.fault_error_code is not None:
            return f"ER,{main},{self.fault_error_code}".encode()
        try:
            body = self._dispatch(main, fields[1:])
        except _RejectError as rej:
            return f"ER,{main},{ERR[self.model][rej.kind]}".encode()
        return body.encode()

    def _need(self, args: list[str], n: int) -> None:
        if len(args) != n:
            raise _RejectError("count")

    def _int(self, s: str, lo: int, hi: int) -> int:
        try:
            v = int(s)
        except ValueError:
            raise _RejectError("param") from None
        if not lo <= v <= hi:
            raise _RejectError("param")
        return v

    def _general(self) -> None:
        if self.comm_mode:
            raise _RejectError("status")

    def _dispatch(self, main: str, args: list[str]) -> str:
        g3000 = self.model == "LK-G3000"
        if main in ("Q0", "R0"):  # enter communication / general mode
            self._need(args, 0)
            # R0 in general mode (Q0 in communication mode) is echoed: [C] both public drivers send R0
            # unconditionally at start-up and check for the echo; the pages read do not say otherwise.
            self.comm_mode = main == "Q0"
            return main
        if main == "SW":
            if not self.comm_mode:
                raise _RejectError("status")
            return self._setting(args)
        if main == "PR":
            self._need(args, 0)
            return f"PR,{self.program}"
        if g3000 and main in ("M0", "M1", "M2"):  # measured value, both OUTs / OUT1 / OUT2 [C] DESY
            self._need(args, 0)
            self._general()
            if main == "M0":
                return f"M0,{self.measure(1)},{self.measure(2)}"
            return f"{main},{self.measure(int(main[1]))}"
        if g3000 and main in ("KL", "VR", "PW"):  # panel lock 0/1, reset OUT 1/2, program change 0–7 [C] DESY
            self._need(args, 1)
            value = self._int(args[0], *{"KL": (0, 1), "VR": (1, OUTS[self.model]), "PW": (0, 7)}[main])
            if main == "PW":
                self._general()
                self.program = value
            elif main == "KL":
                self.panel_locked = bool(value)
            return main
        if not g3000 and main == "MS":  # one OUT: MS,nn → MS,nn,<value> [C] theion, ugurmengilli
            self._need(args, 1)
            self._general()
            return f"MS,{args[0]},{self.measure(self._int(args[0], 1, OUTS[self.model]))}"
        if not g3000 and main == "MA":  # every OUT with a head: MA,<v>,<v>… [C] theion
            self._need(args, 0)
            self._general()
            return "MA," + ",".join(self.measure(o) for o in range(1, self.outs + 1))
        if not g3000 and main == "MM":  # OUTs by a 12-character 0/1 mask, OUT1 first [C] theion
            self._need(args, 1)
            self._general()
            mask = args[0]
            if len(mask) != OUTS[self.model] or set(mask) - {"0", "1"} or "1" not in mask:
                raise _RejectError("param")
            return f"MM,{mask}," + ",".join(self.measure(i + 1) for i, b in enumerate(mask) if b == "1")
        if main in ("AS", "AP", "AQ", "AN"):
            self._need(args, 0)
            self._general()
            return self._storage(main)
        if main == "AO":
            self._need(args, 3)
            self._general()
            self._int(args[0], 1, self.outs)
            self.plant.observe()
            with self._lock:
                first = self._int(args[1], 0, max(self.n_stored - 1, 0))
                n = self._int(args[2], 1, MAX_AO_POINTS)
                if first + n > self.n_stored:
                    raise _RejectError("param")
                values = self._store[first:first + n]
            return "AO," + value_fields(values, self.head.range_mm)
        raise _RejectError("command")

    def _setting(self, args: list[str]) -> str:
        if not args:
            raise _RejectError("count")
        key = args[0].upper()
        if key == "CA":
            self._need(args, 2)
            self.sampling_code = self._int(args[1], 0, len(SAMPLING_US) - 1)
        elif key == "EB":
            self._need(args, 2)
            self.storage_cycle_code = self._int(args[1], 0, len(STORAGE_CYCLES) - 1)
        elif key == "EC":
            self._need(args, 2)
            if len(args[1]) != 7 or args[1][0] not in "+-":
                raise _RejectError("param")
            self.storage_points = self._int(args[1], 1, self.capacity)
        elif key == "OC" and len(args) >= 4:  # SW,OC,<out>,0,<code>: averaging 4**code times (the noise follows)
            self.averaging = LKG_AVERAGING[self._int(args[-1], 0, len(LKG_AVERAGING) - 1)]
            self._set_noise()
        elif key in ("HA", "HB", "HE", "OC"):
            pass  # ABLE, material mode, mounting (and an OC without its value): accepted, no effect on the model
        else:
            raise _RejectError("param")
        return f"SW,{key}"

    def _storage(self, main: str) -> str:
        now = self.clock.now()
        self.plant.advance_to(now)
        with self._lock:
            if main == "AQ":
                if self.storing:
                    raise _RejectError("status")
                self.n_stored = 0
            elif main == "AS":
                if self.storing:
                    raise _RejectError("status")
                self.storing = True
                if self._store.size < self.storage_points:
                    self._store = np.empty(self.storage_points)
                self._next_sample_t = now  # first point at the moment storage starts
            elif main == "AP":
                self.storing = False
            else:
                return f"AN,{1 if self.storing else 0},{self.n_stored}"
        return main
