"""The T7 twin's coupling to the plant: the observables' history its inputs sample, the amplifier input its DAC
drives, and the scan clock both run on.

[D] scan k at t_enable + (k+1)/rate; [A] all samples of a scan taken at that instant (the mux is µs apart).
Wiring: DAC ``dac`` drives the amplifier's input through the rig's conditioning stage (``gain``·V + ``offset``); each
wired AIN reads ``gain``·observable + ``offset`` of the plant (TREK voltage and current monitors, load-cell bridge
amplifier, laser analog output).
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Iterable

import numpy as np

from bench.core.clock import Clock
from bench.core.plant import Plant, PlantBlock
from sim_devices.t7 import analog
from sim_devices.t7.analog import AIN_GROUND, AIN_TEMPERATURE, Conditioning, Signal, default_signals

_NO_NOISE = np.zeros(0)  # an input read without noise (analog.ain_codes_of)


class PlantCoupling:
    """Plant history, AIN sampling, DAC conversion and the amplifier-input drive of one T7 twin."""

    def __init__(self, plant: Plant, clock: Clock, *, dac: int, conditioning: Conditioning | None,
                 signals: dict[int, Signal] | None, calibration: list[float] | None, seed: int,
                 noise: bool = True) -> None:
        self.plant, self.clock = plant, clock
        self.dac = dac
        self.conditioning = conditioning or Conditioning()
        self.signals = default_signals() if signals is None else signals
        self.cal = list(calibration or analog.nominal_calibration())
        self.seed = seed
        self._rngs: dict[tuple[int, int], np.random.Generator] = {}  # one per input and scan-list slot: _noise
        self.noise = noise  # False: every input reads its noiseless value (golden tests; rig option [sim] noise)
        self.lock = threading.RLock()
        self._hist_lock = threading.Lock()  # the plant's listener takes only this one (no lock cycle)
        self._hist_t: deque[np.ndarray] = deque()
        self._hist: deque[dict[str, np.ndarray]] = deque()
        self.errors: list[BaseException] = []
        self.rate = 0.0  # actual scan rate
        self.streaming = False
        self.t_enable = 0.0
        self._filter_y: float | None = None  # reconstruction filter state [V at the amplifier input]
        self._on_block(plant.last)
        plant.listeners.append(self._on_block)

    def _cur_scan(self, now: float) -> int:
        """Index of the last scan that has run (−1: none)."""
        return math.floor((now - self.t_enable) * self.rate + 1e-6) - 1

    def _on_block(self, block: PlantBlock) -> None:
        c = np.ascontiguousarray  # a block's arrays are its own (the plant never writes them again): kept as they
        with self._hist_lock:  # are, a column of a larger array copied (it would keep the whole array alive)
            self._hist_t.append(c(block.t))
            self._hist.append({"voltage": c(block.voltage), "current": c(block.current), "force": c(block.force),
                               "displacement": c(block.displacement)})
            while len(self._hist_t) > 2 and self._hist_t[1][-1] < self.clock.now() - 2.0:
                self._hist_t.popleft()
                self._hist.popleft()

    def _observe(self, times: np.ndarray, keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
        """Plant observables held at the last model step at or before each time (``keys``: only these; None:
        all four)."""
        self.plant.advance_to(float(times[-1]))
        with self._hist_lock:
            first = len(self._hist_t) - 1  # only the blocks that cover the requested times (and the one before)
            while first > 0 and self._hist_t[first][0] > times[0]:
                first -= 1
            if first == len(self._hist_t) - 1:  # one block covers them all (a pump's usual case): nothing to join
                t = self._hist_t[first]
            else:
                t = np.concatenate([self._hist_t[i] for i in range(first, len(self._hist_t))])
            blocks = [self._hist[i] for i in range(first, len(self._hist))]
            idx = analog.held_index(t, times)
            names = blocks[0] if keys is None else keys
            if len(blocks) == 1:
                return {k: blocks[0][k][idx] for k in names}
            return {k: np.concatenate([h[k] for h in blocks])[idx] for k in names}

    def _ain_volts(self, ain: int, obs: dict[str, np.ndarray], n: int, adc_rms: float = 0.0, *,
                   slot: int = -1) -> np.ndarray:
        """``n`` samples of input ``ain`` [V]: what is wired to it plus, when the twin's ``noise`` is on, Gaussian
        noise of the signal's own rms and the ADC's ``adc_rms`` (the resolution index's,
        :mod:`~sim_devices.t7.resolution`), independent, so drawn as one of √(σ_signal² + σ_adc²); ``slot``: the
        sample's place in the stream's scan list (−1: a command-response read)."""
        sig = self.signals.get(ain)
        if ain == AIN_TEMPERATURE:
            v = np.full(n, analog.temperature_volts(self.cal))
        elif sig is None or ain == AIN_GROUND:
            v = np.zeros(n)
        else:
            x = obs[sig.observable]
            v = sig.gain * (x if np.isfinite(x).all() else np.nan_to_num(x)) + sig.offset
        own = sig.noise if sig is not None and ain not in (AIN_TEMPERATURE, AIN_GROUND) else 0.0
        rms = math.hypot(own, adc_rms)
        if rms and self.noise:
            v = v + self._noise(ain, slot).normal(0.0, rms, n)
        return np.asarray(v, float)

    def _ain_stream_codes(self, ain: int, obs: dict[str, np.ndarray], n: int, adc_rms: float, slot: int,
                          gain: int, out: np.ndarray) -> None:
        """``out`` ← the stream codes of ``n`` samples of input ``ain`` on calibration gain index ``gain``: the codes
        of :meth:`_ain_volts` (the same noise draws), a wired input's in one compiled pass
        (:func:`~sim_devices.t7.analog.ain_codes_of`)."""
        sig = self.signals.get(ain)
        if sig is None or ain in (AIN_TEMPERATURE, AIN_GROUND):
            out[:] = self._raw(self._ain_volts(ain, obs, n, adc_rms, slot=slot), gain)
            return
        x = np.ascontiguousarray(obs[sig.observable], dtype=float)  # non-finite values: the kernel's nan_to_num
        rms = math.hypot(sig.noise, adc_rms)
        noise = self._noise(ain, slot).normal(0.0, rms, n) if rms and self.noise else _NO_NOISE
        p, nslope, c = self.cal[4 * gain:4 * gain + 3]
        analog.ain_codes_of(x, float(sig.gain), float(sig.offset), noise, p, nslope, c, out)

    def _ain_scan_block(self, ains: list[int], obs: dict[str, np.ndarray], n: int, adc_rms: list[float],
                        gains: list[int]) -> np.ndarray | None:
        """The stream codes of ``n`` scans of the inputs ``ains`` (scan-list slots 0, 1, …), interleaved in scan order:
        :meth:`_ain_stream_codes` of each (the same noise draws, the same codes) in one compiled pass
        (:func:`~sim_devices.t7.analog.ain_scan_codes`); ``adc_rms``, ``gains``: each input's ADC noise and
        calibration gain index. None when an input reads no plant observable (temperature, ground, nothing wired):
        those take :meth:`_ain_stream_codes`."""
        sigs = [self.signals.get(a) for a in ains]
        if any(sig is None or a in (AIN_TEMPERATURE, AIN_GROUND) for a, sig in zip(ains, sigs, strict=True)):
            return None  # before any draw: those inputs' generators are the per-input path's
        m = len(ains)
        xs = np.empty((m, n))
        params = np.empty((m, 6))
        normals = np.empty((m, n))
        for j, (a, sig) in enumerate(zip(ains, sigs, strict=True)):
            assert sig is not None
            xs[j] = obs[sig.observable]
            rms = math.hypot(sig.noise, adc_rms[j]) if self.noise else 0.0
            if rms:
                self._noise(a, j).standard_normal(out=normals[j])
            g = 4 * gains[j]
            params[j] = (sig.gain, sig.offset, rms, self.cal[g], self.cal[g + 1], self.cal[g + 2])
        out = np.empty((n, m), np.uint16)
        analog.ain_scan_codes(xs, params, normals, out)
        return out.reshape(-1)

    def _noise(self, ain: int, slot: int) -> np.random.Generator:
        """The generator of input ``ain``'s samples at scan-list ``slot`` (−1: its command-response reads), seeded
        from the twin's seed: one draw per sample in sample order, so a run repeats whatever the pumps' sizes."""
        key = (ain, slot)
        if key not in self._rngs:
            self._rngs[key] = np.random.default_rng([self.seed, ain, slot + 1])
        return self._rngs[key]

    def _raw(self, volts: np.ndarray, gain: int) -> np.ndarray:
        return analog.ain_codes(self.cal, volts, gain)

    def _code(self, volts: float, ch: int) -> int:
        return analog.dac_code(self.cal, volts, ch)

    def _code_volts(self, code: int, ch: int) -> float:
        return analog.dac_volts(self.cal, code, ch)

    def _codes_volts(self, codes: np.ndarray, ch: int) -> np.ndarray:
        return analog.dac_codes_volts(self.cal, codes, ch)

    def _drive(self, first: int, codes: np.ndarray) -> np.ndarray | None:
        """Amplifier input events for DAC values played at scans ``first``, ``first`` + 1, …; returns the
        reconstruction filter's output at each (None without a filter)."""
        cond = self.conditioning  # t_enable + (first + 1 + k)/rate and conditioning(_codes_volts(codes)), compiled
        slope, off = self.cal[32 + 2 * self.dac:34 + 2 * self.dac]
        times, volts = analog.dac_drive(first, np.ascontiguousarray(codes, dtype=np.int64), self.t_enable, self.rate,
                                        slope, off, cond.gain, cond.offset, cond.limit)
        fc = cond.corner_Hz
        filtered = None
        if fc is not None and volts.size:  # exact first-order low-pass at the scan instants
            alpha = 1.0 - math.exp(-2.0 * math.pi * fc / self.rate)
            y = self.plant.v_in if self._filter_y is None else self._filter_y
            volts = analog.reconstruct(volts, alpha, float(y))  # lfilter's doubles, compiled
            self._filter_y = float(volts[-1])
            filtered = volts
        try:
            self.plant.schedule_amplifier_scans(times, volts)  # its arrays, on the scan clock (dac_drive's times)
        except ValueError as exc:  # cannot happen under the lock order; kept as a check
            self.errors.append(RuntimeError(f"DAC value: {exc}"))
        return filtered

    def _undrive_after(self, t: float) -> None:
        self.plant.unschedule_amplifier_input(t)
