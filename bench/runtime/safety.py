"""Safety supervisor: every set-point and every incoming sample checked against the limits.

Limits come from the rig file (``[limits]``) and from the specimen: the true electric field is estimated
from the latest measured stretch — membrane: λ = λ_pre + u/L_d from the laser, E = Vλ²/L3 against the
breakdown field; LS-DEA: aperture x from the motor encoder or the laser, E = Vλ1λ2/t0 against the
stretch-dependent E_B = E0 λ3^(−r/2). A set-point that would exceed a limit is not sent — checked as sent,
on the module's code, chosen within :meth:`Supervisor.setpoint_bound`; a sample beyond a limit trips the run.
A trip raises :class:`SafetyTrip`; the engine then brings the rig to its safe state.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

from bench.models.lozenge import LozengeParams, kinematics
from bench.models.lozenge import capacitance as lozenge_capacitance
from bench.models.membrane import MembraneParams
from bench.models.membrane import capacitance as membrane_capacitance
from bench.numbers import against
from bench.rig import MONITOR_TRIP_FACTOR, MONITOR_TRIP_MARGIN_V, RigConfig


class SafetyTrip(Exception):  # noqa: N818 - a trip is not an error of the program
    """A limit was reached; ``reason`` is one line naming the quantity and the limit."""

    def __init__(self, reason: str) -> None:
        self.reason = reason
        super().__init__(reason)


@dataclass
class Supervisor:
    """Limits of one run and the latest measured state they are checked against."""

    rig: RigConfig
    specimen: MembraneParams | LozengeParams
    voltage_limit: float = field(init=False)
    last_voltage: float = 0.0
    last_current: float = 0.0
    last_force: float = 0.0
    displacement: float | None = None  # membrane u [m]
    aperture: float | None = None  # LS-DEA x [m]
    motor_setpoints: int = 0  # go-to commands checked (and passed)
    _last_stretch: tuple[LozengeParams, float, tuple[float, float, float]] | None = field(
        default=None, init=False, repr=False, compare=False)  # (specimen, aperture, _stretch's answer)
    _last_headroom: tuple[object, object, tuple[float | None, ...], dict[str, float]] | None = field(
        default=None, init=False, repr=False, compare=False)  # (specimen, rig, the values it read, headroom())

    def __post_init__(self) -> None:
        lim = self.rig.limits.max_voltage_V
        if self.rig.amplifier is not None:
            lim = min(lim, self.rig.amplifier.max_voltage_V)
        self.voltage_limit = lim
        if isinstance(self.specimen, LozengeParams):
            cfg = self.rig.specimen.lsdea
            self.aperture = cfg.blocked_position_m if cfg.configuration == "blocked" else cfg.x_at_motor_zero_m
        else:
            self.displacement = 0.0

    # ------------------------------------------------------------ field model
    def field_and_breakdown(self, volts: float) -> tuple[float, float]:
        """(true field [V/m], field at which to trip [V/m]) for ``volts`` at the last measured stretch."""
        margin = self.rig.limits.breakdown_margin
        cap = self.rig.limits.max_field_V_per_m or math.inf
        if isinstance(self.specimen, MembraneParams):
            p = self.specimen
            lam = p.lambda_pre + (self.displacement or 0.0) / p.L_d
            return abs(volts) * lam * lam / p.L3, min(cap, p.breakdown_field / margin)
        q = self.specimen
        x = min(max(self.aperture or q.xp, 1.0001 * q.xp), 1.999 * q.l)
        l1, l2, e_b = self._stretch(q, x)
        return abs(volts) * l1 * l2 / q.t0, min(cap, e_b / margin)

    def field_bounded(self, volts: float) -> bool:
        """Whether ``volts`` stays within the field limit whatever the stretch: then an unknown stretch is no danger.
        A membrane's up to its runaway stretch (past which it has failed anyway). An LS-DEA's at every aperture
        :meth:`field_and_breakdown` judges (``x`` in [1.0001 xp, 1.999 l]): E = |V|·A/t0 against E_B = E0·A^(r/2)
        (and the field cap), A = λ1λ2 ∝ x·√(4l² − x²); both ratios are monotone in A, so the worst aperture is the
        one of least or of most A — an end of the range, or x = √2·l, where x·√(4l² − x²) peaks. (The LS-DEA had
        no bound: a laser out of range on an isotonic rig tripped manual control at any voltage.)"""
        lim = self.rig.limits
        cap = lim.max_field_V_per_m or math.inf
        if isinstance(self.specimen, MembraneParams):
            p = self.specimen
            return abs(volts) * p.runaway_stretch ** 2 / p.L3 <= min(cap, p.breakdown_field / lim.breakdown_margin)
        q = self.specimen
        apertures = [1.0001 * q.xp, 1.999 * q.l] + ([math.sqrt(2.0) * q.l] if q.xp < math.sqrt(2.0) * q.l else [])
        for x in apertures:
            l1, l2, e_b = self._stretch(q, x)
            if abs(volts) * l1 * l2 / q.t0 > min(cap, e_b / lim.breakdown_margin):
                return False
        return True

    def capacitance(self) -> float:
        """The specimen's capacitance [F] at the last measured stretch (as :meth:`field_and_breakdown` takes it; a
        membrane at the rig file's specimen temperature, on which its permittivity depends)."""
        if isinstance(self.specimen, MembraneParams):
            p = self.specimen
            lam = p.lambda_pre + (self.displacement or 0.0) / p.L_d
            return float(membrane_capacitance(lam, self.rig.specimen.temperature_K, p.pack())[0])
        q = self.specimen
        x = min(max(self.aperture or q.xp, 1.0001 * q.xp), 1.999 * q.l)
        return float(lozenge_capacitance(x, q.pack())[0])

    def _stretch(self, q: LozengeParams, x: float) -> tuple[float, float, float]:
        """(λ1, λ2, breakdown field E_B [V/m]) of the LS-DEA ``q`` at aperture ``x`` [m]: the last one remembered, as
        the aperture changes only with a motor reading (the live view's headroom asks at every engine wake-up, and
        packing the specimen for the kinematics costs more than the rest of the field model)."""
        last = self._last_stretch
        if last is not None and last[0] is q and last[1] == x:
            return last[2]
        l1, l2, *_ = kinematics(x, q.pack())
        out = l1, l2, q.material.E0 * (l1 * l2) ** (q.material.r / 2)
        self._last_stretch = q, x, out
        return out

    # ------------------------------------------------------------ checks
    def check_setpoint(self, volts: float) -> None:
        """Refuse a voltage set-point beyond the voltage limit or the field limit at the present stretch."""
        if not math.isfinite(volts):
            self._trip(f"set-point {volts} V is not a number")
        if abs(volts) > self.voltage_limit + 1e-9:
            self._trip(f"set-point {volts:.0f} V beyond the voltage limit ±{self.voltage_limit:.0f} V")
        e, e_max = self.field_and_breakdown(volts)
        if not e <= e_max:  # also trips when the estimate is NaN: an unknown field is not a safe one
            field_text, limit_text = against(e, e_max, 1e-6)
            self._trip(f"set-point {volts:.0f} V would give a true field of {field_text} MV/m, limit "
                       f"{limit_text} MV/m at the present stretch")

    def setpoint_bound(self) -> float:
        """The largest |V| [V] :meth:`check_setpoint` passes at the present stretch: the voltage limit, or less where
        the field limit binds (the true field is proportional to |V|). Drivers choose the code sent within ±this
        bound, so that a set-point at a limit runs and the value sent never lies beyond it."""
        bound = self.voltage_limit
        e, e_max = self.field_and_breakdown(bound)
        if e <= e_max or not (0 < e < math.inf and 0 <= e_max < math.inf):
            return bound  # an unknown field: check_setpoint refuses the value itself
        bound *= e_max / e
        while bound > 0 and not self.field_and_breakdown(bound)[0] <= e_max:  # the last bits of the division
            bound = math.nextafter(bound, 0.0)
        return bound

    def check_setpoint_over(self, volts: float, apertures: Sequence[float]) -> None:
        """:meth:`check_setpoint` at the present aperture and at each of ``apertures`` (LS-DEA: values that will
        play while the motor moves there; a membrane has no aperture)."""
        self.check_setpoint(volts)
        for x in self._other_apertures(apertures):
            with self._at_aperture(x):
                self.check_setpoint(volts)

    def setpoint_bound_over(self, apertures: Sequence[float]) -> float:
        """The smallest :meth:`setpoint_bound` at the present aperture and at each of ``apertures``."""
        bound = self.setpoint_bound()
        for x in self._other_apertures(apertures):
            with self._at_aperture(x):
                bound = min(bound, self.setpoint_bound())
        return bound

    def _other_apertures(self, apertures: Sequence[float]) -> list[float]:
        """The apertures to check besides the present one — and √2·l, where λ1·λ2 and the true field at a voltage
        peak, when they and the present one span it (between it the field is monotonic: the ends bound it)."""
        if not isinstance(self.specimen, LozengeParams):
            return []
        bad = [x for x in apertures if not math.isfinite(x)]
        if bad:
            self._trip(f"aperture {bad[0]} m is not a number")
        xs = [x for x in apertures if x != self.aperture]
        span = [*xs, *([self.aperture] if self.aperture is not None else [])]
        peak = math.sqrt(2.0) * self.specimen.l
        if span and min(span) < peak < max(span):
            xs.append(peak)
        return xs

    @contextlib.contextmanager
    def _at_aperture(self, x: float) -> Iterator[None]:
        """The field model evaluated at aperture ``x`` (the measured one restored after)."""
        present, self.aperture = self.aperture, x
        try:
            yield
        finally:
            self.aperture = present

    def check_monitors(self, volts: float, amps: float) -> None:
        """Output voltage and current from the amplifier monitors."""
        if not (math.isfinite(volts) and math.isfinite(amps)):
            self._trip(f"amplifier monitors read {volts} V, {amps} A: not a measurement")
        self.last_voltage, self.last_current = volts, amps
        if abs(amps) > self.rig.limits.max_current_A:
            value, limit = against(amps, self.rig.limits.max_current_A, 1e3)
            self._trip(f"current {value} mA beyond the trip level {limit} mA")
        if abs(volts) > self.voltage_limit * MONITOR_TRIP_FACTOR + MONITOR_TRIP_MARGIN_V:
            self._trip(f"output {volts:.0f} V beyond the voltage limit ±{self.voltage_limit:.0f} V")
        e, e_max = self.field_and_breakdown(volts)
        if not e <= e_max:
            field_text, limit_text = against(e, e_max, 1e-6)
            self._trip(f"true field {field_text} MV/m beyond the limit {limit_text} MV/m")

    def check_force(self, newtons: float) -> None:
        """Load-cell force."""
        if not math.isfinite(newtons):
            self._trip(f"load cell reads {newtons} N: not a measurement")
        self.last_force = newtons
        if abs(newtons) > self.rig.limits.max_force_N:
            value, limit = against(newtons, self.rig.limits.max_force_N)
            self._trip(f"force {value} N beyond the limit ±{limit} N")

    def check_motor(self, motor_position: float, aperture: float) -> None:
        """Motor encoder position against the travel limits; updates the aperture estimate."""
        self.aperture = aperture
        m = self.rig.motor
        if m is None:
            return
        tol = self.rig.limits.travel_tolerance_m
        if not m.travel_m[0] - tol <= motor_position <= m.travel_m[1] + tol:
            self._trip(f"motor at {motor_position * 1e3:.2f} mm, outside travel "
                       f"[{m.travel_m[0] * 1e3:.1f}, {m.travel_m[1] * 1e3:.1f}] mm")

    def check_motor_setpoint(self, motor_position: float, aperture: float, volts: float) -> None:
        """Refuse a motor go-to outside the travel limits, or one whose aperture would put the present voltage
        beyond the field limit (the LS-DEA's field depends on its stretch, hence on the aperture)."""
        m = self.rig.motor
        if not math.isfinite(motor_position):
            self._trip(f"motor set-point {motor_position} m is not a number")
        if m is not None and not m.travel_m[0] <= motor_position <= m.travel_m[1]:
            self._trip(f"motor set-point {motor_position * 1e3:.2f} mm outside travel "
                       f"[{m.travel_m[0] * 1e3:.1f}, {m.travel_m[1] * 1e3:.1f}] mm")
        if isinstance(self.specimen, LozengeParams) and math.isfinite(aperture) and volts != 0.0:
            for x in self._path(aperture):
                with self._at_aperture(x):
                    e, e_max = self.field_and_breakdown(volts)
                if not e <= e_max:
                    where = "" if x == aperture else f" (passing {x * 1e3:.1f} mm on the way)"
                    field_text, limit_text = against(e, e_max, 1e-6)
                    self._trip(f"motor set-point to aperture {aperture * 1e3:.1f} mm at {volts:.0f} V would give a "
                               f"true field of {field_text} MV/m{where}, limit {limit_text} MV/m")
        self.motor_setpoints += 1

    def _path(self, target: float, samples: int = 16) -> list[float]:
        """Apertures a go-to to ``target`` passes, the target last: evenly spaced from the present aperture, and
        √2·l where the path crosses it (:meth:`_other_apertures`: a path over the field's peak may exceed the limit
        in its middle while both ends are within)."""
        start = self.aperture if self.aperture is not None and math.isfinite(self.aperture) else target
        path = [start + (target - start) * k / samples for k in range(1, samples)]
        return [*self._other_apertures(path), target]

    def update_displacement(self, value: float) -> None:
        """Latest laser value in specimen coordinates (membrane u, or LS-DEA aperture x) [m]."""
        if not math.isfinite(value):
            return  # not a measurement: the estimate keeps the last one
        if isinstance(self.specimen, MembraneParams):
            self.displacement = value
            lam = self.specimen.lambda_pre + value / self.specimen.L_d
            if lam > self.specimen.runaway_stretch:
                self._trip(f"stretch {lam:.2f} beyond {self.specimen.runaway_stretch:g}: runaway (pull-in)")
        else:
            self.aperture = value

    def headroom(self) -> dict[str, float]:
        """Fraction of each limit in use (0…1+), for the live view (a new dict at each call). The engine asks at every
        wake-up (each 20-Hz position poll) while the values it depends on change far less often (the monitors at a
        DAQ collect): the last answer is given again while the specimen, the rig (both frozen) and the values read
        here are the same."""
        values = (self.last_voltage, self.last_current, self.last_force, self.displacement, self.aperture,
                  self.voltage_limit)
        last = self._last_headroom
        if last is not None and last[0] is self.specimen and last[1] is self.rig and last[2] == values:
            return dict(last[3])
        e, e_max = self.field_and_breakdown(self.last_voltage)
        out = {"voltage": abs(self.last_voltage) / self.voltage_limit, "field": e / e_max,
               "current": abs(self.last_current) / self.rig.limits.max_current_A,
               "force": abs(self.last_force) / self.rig.limits.max_force_N}
        self._last_headroom = self.specimen, self.rig, values, out
        return dict(out)

    def _trip(self, reason: str) -> None:
        raise SafetyTrip(reason)
