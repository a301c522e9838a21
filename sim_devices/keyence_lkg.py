"""Simulated Keyence LK-G3000 / LK-G5000 controller speaking its RS-232C ASCII protocol on a pty.

Behaviour modelled: general vs communication mode (settings refused in general mode and vice versa with
the model's status-error code), the 8-character value format with over-range (``±FFFFFFF``) and invalid
(``XXXXXXXX``) values, 0.1-µm display quantisation, seeded Gaussian noise, the measuring range of the head,
data storage filled from the plant at the configured cycle up to a capacity, error replies to unknown,
malformed or mis-parameterised commands. The command set and the storage parameters are those of
:mod:`drivers.keyence` (which documents what is verified and what is assumed).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from drivers.keyence import SAMPLING_US, STORAGE_CYCLES, Model, format_value, format_values
from sim_devices.clock import Clock
from sim_devices.plant import Plant, PlantBlock

ERR = {"LK-G3000": {"command": "00", "status": "01", "length": "20", "count": "21", "param": "22"},
       "LK-G5000": {"command": "50", "status": "51", "length": "60", "count": "61", "param": "62"}}


@dataclass
class LaserHead:
    """Measuring geometry of the head: reading [mm] = offset + sign × 1000 × plant displacement [m]."""

    offset_mm: float = 0.0
    sign: float = 1.0
    range_mm: float = 40.0  # ± measuring range around the reference distance (LK-G152/LK-H152: ±40 mm)
    noise_mm: float = 0.0002  # rms (0.2 µm)


class _RejectError(Exception):
    def __init__(self, kind: str) -> None:
        self.kind = kind


class KeyenceLKGSim:
    """Protocol handler of the simulated controller (feed it bytes; it returns the reply bytes)."""

    def __init__(self, plant: Plant, clock: Clock, *, model: Model = "LK-G3000", head: LaserHead | None = None,
                 capacity: int = 65_536, seed: int = 1, outs: int = 2) -> None:
        self.plant = plant
        self.clock = clock
        self.model: Model = model
        self.head = head or LaserHead()
        self.capacity = capacity
        self.outs = outs
        self.rng = np.random.default_rng(seed)
        self.comm_mode = False
        self.program = 0
        self.sampling_code = 2  # 100 µs
        self.storage_cycle_code = 0
        self.storage_points = capacity
        self.storing = False
        self._store = np.empty(0)  # storage memory [mm] (NaN = invalid), allocated when storage starts
        self.n_stored = 0
        self._next_sample_t = 0.0
        self._prev: tuple[float, float] | None = None  # last (t, displacement) seen, for interpolation
        self._buf = b""
        self._lock = threading.Lock()
        self.fault_error_code: str | None = None  # answer every command with ER,<cmd>,<code> while set
        plant.listeners.append(self._on_block)

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
        if not math.isfinite(mm):
            return format_value(None, "invalid")
        if mm > self.head.range_mm:
            return format_value(None, "over_range_positive")
        if mm < -self.head.range_mm:
            return format_value(None, "over_range_negative")
        return format_value(round(mm, 4))

    def measure(self) -> str:
        """Current reading of OUT1 as an 8-character field."""
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
        if main == "Q0":
            self._need(args, 0)
            self.comm_mode = True
            return "Q0"
        if main == "R0":
            self._need(args, 0)
            if not self.comm_mode:
                raise _RejectError("status")
            self.comm_mode = False
            return "R0"
        if main == "SW":
            if not self.comm_mode:
                raise _RejectError("status")
            return self._setting(args)
        if main == "PR":
            self._need(args, 0)
            return f"PR,{self.program}"
        if self.model == "LK-G3000" and main in ("M0", "M1", "M2"):
            self._need(args, 0)
            self._general()
            if main == "M0":
                v = self.measure()
                return f"M0,{v},{self._value_field(math.nan)}"
            if main == "M2" and self.outs < 2:
                raise _RejectError("param")
            return f"{main},{self.measure() if main == 'M1' else self._value_field(math.nan)}"
        if self.model == "LK-G5000" and main == "MS":
            self._need(args, 1)
            self._general()
            out = self._int(args[0], 1, 12)
            return f"MS,{args[0]},{self.measure() if out == 1 else self._value_field(math.nan)}"
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
                n = self._int(args[2], 1, 1000)
                if first + n > self.n_stored:
                    raise _RejectError("param")
                values = self._store[first:first + n]
            return "AO," + format_values(values, self.head.range_mm).decode()
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
        elif key in ("HA", "HB", "HE", "OC"):
            pass  # ABLE, material mode, mounting, averaging: accepted, no effect on the model
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
