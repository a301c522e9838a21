"""Manual mode of the engine: commands instead of a program, on the one executor.

As labscript BLACS's ``transition_to_manual`` / ``transition_to_buffered``, manual control is a mode of the same
executor, not a second one: :class:`ManualEngine` is the :class:`~bench.runtime.engine.Engine` with an empty
program, its set-points command-response (no DAQ stream plays), and entry points for typed commands. Every
voltage goes through the engine's ``_set_voltage`` (the supervisor on the request and on the value after DAC
rounding, the host-stall guard, the output verifier, the set-points stream), every ramp through ``_ramp_to``,
every go-to through ``_move_motor`` (the drive's increment, the travel and field checks), a pause through
``_make_paused`` (ramp to 0 V, motor stopped), and the session's end through ``_shut_down`` (the bounded stop:
ramp over ``shutdown_ramp_s``, at once on a second request or a latch; every instrument safe; 0 V verified on the
monitor). Stop signals are the engine's handlers (:meth:`~bench.runtime.engine.Engine.signals`).

What a manual session adds: a command the latch, a pause or the supervisor does not allow is :class:`Refused`
(nothing sent) instead of ending anything; a trip zeroes the output at once and the session goes on; an
interlock fault latches until :meth:`ManualEngine.reset_latch`; a pause holds 0 V until :meth:`ManualEngine.resume`.

Nothing follows the stop's zero: once the stop has begun every set-point is refused (:class:`Refused`, nothing sent)
and a keep-alive sends nothing. The set-point lock makes the two one after the other: a set-point already going
out (the session's keep-alive thread) is sent before the stop begins, never after its ramp and zero.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

from bench.core.clock import Clock
from bench.core.noise import TREK_DYNAMICS
from bench.core.step_current import largest_step, monitor_peak
from bench.numbers import whole
from bench.protocol.program import Program
from bench.protocol.schema import Protocol, ProtocolHeader
from bench.rig import RigConfig
from bench.runtime.engine import (
    DISCHARGE_WAIT_S,
    MONITOR_REREAD_S,
    MONITOR_SETTLE_S,
    Engine,
    PauseRequested,
    StopRequested,
)
from bench.runtime.instruments import Instruments
from bench.runtime.interlock import OUTPUT_ON_V, InterlockTrip, OutputVerifier, motion_trip
from bench.runtime.polls import rig_polls
from bench.runtime.safety import SafetyTrip, Supervisor
from bench.storage.recorder import Recorder
from drivers.errors import InstrumentError, InstrumentStateError

LASER_LOST_S = 0.5  # the laser reading no displacement this long with the output on trips a session (5 reads)
KEEPALIVE_S = 0.25  # set-point refresh while holding (feeds the analog module's communication watchdog)
IDLE_MIN_S = 1e-3  # a hold waits at least this long between two idle actions (no busy loop on a late schedule)
MOVE_POLL_S = 0.05  # a move's status is read this often until it ends
MOVE_ACCEL = 0.5  # m/s², a manual move's acceleration (at most the rig's)
MOVE_SPARE_S = 2.0  # a move must end within its distance / speed × 1.5 plus this
RAMP_HZ = 20.0  # set-points per second of a `ramp` command
STEP_MARGIN = 0.5  # a refused step's named ramp keeps each set-point within this share of the largest step allowed

__all__ = ["KEEPALIVE_S", "RAMP_HZ", "LatchRefused", "ManualEngine", "PauseRequested", "Refused", "StopRequested",
           "manual_program"]


class Refused(Exception):  # noqa: N818 - a refusal is an outcome, not a program error
    """A command the latch, a pause, the supervisor (or its syntax) does not allow; nothing was sent."""


class LatchRefused(Refused):
    """A command refused because the rig is latched (or a reset a script asked for): a script stops at it, as at a
    trip — the commands after it were written for a rig that is not latched."""


def manual_program(rig: RigConfig) -> Program:
    """The program of a manual session: no steps (the commands are the program)."""
    header = ProtocolHeader.model_construct(name="manual control", rig=rig.name)
    return Program(Protocol.model_construct(protocol=header, steps=[]), rig, [])


class ManualEngine(Engine):
    """The engine in manual mode on connected instruments; run time 0 is ``t0`` on ``clock``."""

    def __init__(self, rig: RigConfig, inst: Instruments, clock: Clock, recorder: Recorder,
                 supervisor: Supervisor, t0: float) -> None:
        super().__init__(manual_program(rig), inst, clock, recorder, supervisor, commands=True)
        self.ctx.laser_lost_s = LASER_LOST_S  # no dry run covers a session: an unknown stretch at high voltage trips
        self.rig = rig
        self.ctx.t0 = t0
        self.snapshot.state = "manual"
        self._polls = {p.name: p for p in rig_polls(self.ctx)}  # the rig's polls: one per instrument it reads
        self.latched_at = 0.0  # run time of the latch [s]
        self.unproven: InterlockTrip | None = None  # make_safe's latch (0 V not commanded): the session records it
        self.paused = False
        self._paused_at = 0.0  # run time of the pause [s]
        self._setpoint_lock = threading.RLock()  # one set-point, or the start of the stop: never interleaved
        self._idle: tuple[Callable[[], None], dict[str, float]] | None = None  # the polls between commands
        self._idle_at = -math.inf  # run time of the last idle poll at 0 V
        self._moving = False  # a manual go-to under way
        if inst.amplifier is not None:  # what connecting left the output at (0 V): the first ramp starts there
            self.ctx.v_cmd = float(inst.amplifier.commanded)
            self.verifier.commanded(self.now(), self.ctx.v_cmd)

    # ------------------------------------------------------------ what holds the output off
    def latch_text(self) -> str:
        assert self.latched is not None
        return (f"interlock latched at t={self.latched_at:.3f} s ({self.latched.kind}): high voltage stays off "
                "until `reset WHY...`")

    def _held(self, volts: float, what: str) -> None:
        """Refused (nothing kept alive) once the stop has begun; while latched or paused, unless ``volts`` is 0."""
        if self._stopping:
            raise Refused(f"{self._ending_text()}; {what}")
        if volts == 0.0:
            return
        if self.latched is not None:
            self.ctx.v_req = 0.0
            raise LatchRefused(f"{self.latch_text()}; {what}")
        if self.paused:
            self.ctx.v_req = 0.0
            raise Refused(f"paused: high voltage stays off until `resume`; {what}")

    def _ending_text(self) -> str:
        return "the session is ending: the stop zeroes the output and nothing may follow it"

    def _set_voltage(self, v: float, t: float, x_cmd: float = math.nan) -> None:
        """The engine's set-point (every set-point of the session: commands, keep-alives, ramps, a pause's ramp),
        under the set-point lock and refused once the stop has begun (Refused, nothing sent)."""
        with self._setpoint_lock:
            if self._stopping:
                raise Refused(f"{self._ending_text()}; not sent")
            super()._set_voltage(v, t, x_cmd)

    def _shut_down(self, state: str, reason: str, finish: bool = True) -> str:
        """The engine's stop, begun under the set-point lock: a set-point in flight is sent first, and none after."""
        with self._setpoint_lock:
            self._stopping = True
        return super()._shut_down(state, reason, finish)

    # ------------------------------------------------------------ voltage
    def voltage(self, volts: float) -> float:
        """One supervised set-point (the engine's ``_set_voltage``); Refused before anything is sent if the latch,
        a pause or the supervisor (on the request or on the value after DAC rounding) does not allow it. Returns
        the value sent. A pause asked for meanwhile (SIGUSR1 at the prompt) comes first: PauseRequested, nothing
        sent. Once the stop has begun: Refused, nothing sent."""
        if self._stopping:
            raise Refused(f"{self._ending_text()}; not sent")
        self._check_pause()
        self._held(volts, "not sent")
        try:
            self._check_voltage(volts)
        except SafetyTrip as exc:
            self.ctx.v_req = self.ctx.v_cmd
            raise Refused(f"{exc.reason}; not sent") from None
        self._check_step(volts, volts - self.ctx.v_cmd, "not sent")
        self._set_voltage(volts, self.now())
        return self.ctx.v_cmd

    def _check_step(self, target: float, dv: float, what: str, ramp_s: float | None = None) -> None:
        """Refused where a step of ``dv`` [V] (a set-point toward ``target``: a ``ramp`` sends its ``ramp_s`` in
        steps at RAMP_HZ) on a DAQ rig would show a charging current above the rig's limit on the current monitor
        (:mod:`bench.core.step_current`, the specimen's capacitance at the present stretch): a protocol's run scans
        that monitor at 10 kHz and trips on it, and validate refuses such an edge; a session's polled monitors never
        see a pulse of a few ms (an outside tester: `voltage 5000` from 0 V on an LS-DEA DAQ rig went out, the same
        edge in a protocol refused at 12 mA). A set-point toward 0 V (0 V itself, or a lower one of the same sign) is
        never refused: the output can always be let down (`voltage 10` from 7 kV was refused while `ramp 0 0.05` went
        out in one 7-kV set-point: an outside tester)."""
        amp, daq = self.rig.amplifier, self.rig.daq
        v0 = self.ctx.v_cmd
        down = abs(target) <= abs(v0) and target * v0 >= 0.0
        if down or dv == 0.0 or amp is None or amp.drive != "daq" or daq is None:
            return
        c, dyn, limit = self.sup.capacitance(), TREK_DYNAMICS[amp.model], self.rig.limits.max_current_A
        if (peak := monitor_peak(dv, c, dyn, daq.drive_filter_Hz)) <= limit:
            return
        # the ramp named keeps each set-point within half the largest step at the present stretch: the stretch grows
        # as the voltage does, and with it the capacitance (a membrane's as λ⁴: twice from λ 2 to 2.38)
        most = largest_step(c, dyn, daq.drive_filter_Hz, limit, abs(dv))
        step = STEP_MARGIN * most
        kind = f"a step of {abs(dv):.0f} V charges" if ramp_s is None else \
            f"the {ramp_s:g}-s ramp's steps of {abs(dv):.0f} V (one every {1 / RAMP_HZ:g} s) each charge"
        span = abs(target - v0)
        how = (f"`ramp {target:.0f} V {math.ceil(span / step) / RAMP_HZ:.2f} s` keeps each step within {step:.0f} V "
               f"(half the {most:.0f} V allowed at the present stretch: the capacitance grows with it)"
               if step >= 1.0 else "no ramp of set-points keeps within it")
        raise Refused(f"{kind} the specimen ({c * 1e9:.2f} nF at the present stretch) at {peak * 1e3:.1f} mA on the "
                      f"current monitor, above the rig's {limit * 1e3:g}-mA limit (a run scanning it would trip); "
                      f"{how}; {what}")

    def reach(self, volts: float) -> float:
        """:meth:`voltage`, re-sent once the amplifier's slew limit allows the whole step (after |gap| / slew on the
        run clock): in virtual time no time passes between two commands, so a first send right after another
        set-point is cut to almost nothing. Returns the set-point finally sent."""
        sent = self.voltage(volts)
        amp = self.rig.amplifier
        slew = amp.slew_limit_V_per_s if amp is not None else math.inf
        need = abs(volts - sent) / slew
        while need > 0:
            nap = min(need, KEEPALIVE_S)
            self._wait(self.now() + nap)
            sent = self.voltage(volts)
            need = 0.0 if nap >= need else abs(volts - sent) / slew
        return sent

    def keep_alive(self) -> None:
        """Re-send the set-point held (feeds the set-point module's watchdog); nothing at 0 V, nothing once the
        stop has begun (a tick that finds it begun meanwhile is refused by :meth:`_set_voltage`)."""
        if self.inst.amplifier is not None and self.ctx.v_req != 0.0 and not self._stopping:
            self.voltage(self.ctx.v_req)

    def ramp(self, target: float, seconds: float, rate_hz: float) -> int:
        """The engine's ``_ramp_to`` at ``rate_hz`` set-points per second, the monitors checked after each; Refused
        before the first if the target is not allowed. Returns the number of set-points."""
        self._check_pause()
        self._held(target, "ramp not started")
        try:
            self.sup.check_setpoint(target)
        except SafetyTrip as exc:
            raise Refused(f"{exc.reason}; ramp not started") from None
        n = max(1, math.ceil(seconds * rate_hz))
        self._check_step(target, (target - self.ctx.v_cmd) / n, "ramp not started", seconds)
        self._ramp_to(target, seconds, n, self._ramp_step_done)
        return n

    def _ramp_step_done(self) -> None:
        """After each set-point of a manual ramp: the monitors checked, the rig's other polls that are due run (the
        laser: the field check's stretch, through a ramp that may last an hour — a reviewer), and a pause asked for
        meanwhile ends the ramp."""
        self.check_monitors()
        self._idle_schedule()[0]()
        self._check_pause()

    def zero(self) -> None:
        """The output to 0 V at once (nothing held)."""
        self.ctx.v_req = 0.0
        self.ctx.amp.zero()
        self._output_is(float(self.ctx.amp.commanded))

    def _output_is(self, volts: float) -> None:
        """The amplifier now outputs ``volts``: what the monitors are checked against; recorded."""
        self.ctx.v_cmd = volts
        self.verifier.commanded(self.now(), volts)
        self._record(self.rec.append, "setpoints", self.now(), voltage=volts, aperture=math.nan)

    # ------------------------------------------------------------ time
    def _wait(self, until: float) -> None:
        """Until run time ``until``, stop and pause requests checked (the run context's wait)."""
        self.ctx.wait_until(until)

    def hold(self, seconds: float) -> None:
        """Let ``seconds`` pass on the run clock, supervised as a run's hold is (:meth:`idle`): the set-point re-sent
        every KEEPALIVE_S, the rig's polls run when due."""
        end = self.now() + seconds
        while end - self.now() > 0:
            self._wait(min(end, max(self.idle_due(), self.now() + IDLE_MIN_S)))
            self.idle()
        self._check_stop()

    def _laser_free(self) -> bool:
        """A session never runs the laser's data storage: its line is free for single reads, which the supervisor's
        field check needs while the output is held — without them a held 8 kV crept the membrane to breakdown with
        the field computed at the stretch of the session's one laser reading (an outside tester)."""
        return self.inst.laser is not None

    def _energised(self) -> bool:
        """The output is on (above ``OUTPUT_ON_V`` commanded or asked for) or the motor has a go-to under way."""
        return (max(abs(self.ctx.v_cmd), abs(self.ctx.v_req)) > OUTPUT_ON_V
                or (self.inst.motor is not None and self._moving))

    def _idle_schedule(self) -> tuple[Callable[[], None], dict[str, float]]:
        """The run's supervised reading outside a step (the engine's :meth:`_supervision`: every polled channel at
        the rate the program's recording gives it, recorded, supervised and verified), made once per session."""
        if self._idle is None:
            self._idle = self._supervision()
        return self._idle

    def idle_due(self) -> float:
        """Run time of the next :meth:`idle` action: the keep-alive while the output is held, the earliest poll due
        while energised, else (0 V, motor still) the polls at the keep-alive's pace."""
        now = self.now()
        due = now + KEEPALIVE_S
        if self.inst.amplifier is not None and self.ctx.v_req != 0.0:
            due = min(due, self._setpoint_t + KEEPALIVE_S)
        if self._energised():
            due = min([due, *self._idle_schedule()[1].values()])
        return due

    def idle(self) -> None:
        """Between commands, in a ``wait`` and in every other hold: what a run's hold step does — the set-point
        re-sent (the host-stall guard before it) once KEEPALIVE_S has gone since the last, and the rig's polls
        (monitors against the current limit and the commanded band, encoder, load cell, sensors) when due. While
        the output is at 0 V and the motor still, the polls slow to the keep-alive's pace. A trip or a latch is
        raised here, without any command: the caller zeroes and latches as after a command."""
        if self._stopping:
            return
        now = self.now()
        if self.inst.amplifier is not None and self.ctx.v_req != 0.0 and now >= self._setpoint_t + KEEPALIVE_S - 1e-3:
            self.keep_alive()
        supervise, _ = self._idle_schedule()
        if self._energised() or now >= self._idle_at + KEEPALIVE_S - 1e-3:
            self._idle_at = now
            supervise()

    def _check_pause(self) -> None:
        if not self.paused:
            super()._check_pause()

    # ------------------------------------------------------------ motor
    def move(self, target: float, speed: float) -> float:
        """A supervised go-to through the engine's ``_move_motor`` (Refused, nothing sent, if the supervisor does
        not allow it), then its status every MOVE_POLL_S until it ends — each position recorded, supervised and
        verified against the go-to (the interlock's motion verifier); returns where the motor stopped."""
        m = self.rig.motor
        assert m is not None  # a motor driver comes from rig.motor
        if not speed > 0:
            raise Refused("speed must be positive")
        if speed > m.max_velocity_m_per_s:  # refused as a protocol's move step is, never capped in silence
            raise Refused(f"speed {speed:g} m/s beyond the rig's {m.max_velocity_m_per_s:g} m/s "
                          "(motor.max_velocity_m_per_s); not sent")
        try:
            x_cmd = self._move_motor(target, speed, min(MOVE_ACCEL, m.max_acceleration_m_per_s2))
        except SafetyTrip as exc:
            raise Refused(f"{exc.reason}; not sent") from None
        self._record(self.rec.append, "setpoints", self.now(), voltage=math.nan, aperture=x_cmd)
        self._moving = True
        try:
            return self._follow(target, speed)
        finally:
            self._moving = False

    def _follow(self, target: float, speed: float) -> float:
        """A go-to sent: its status every MOVE_POLL_S until it ends (:meth:`move`)."""
        motor = self.ctx.motor
        deadline = self.now() + MOVE_SPARE_S + abs(target - motor.read_position().value) / speed * 1.5
        prog = self.program
        while self.now() < deadline:
            self.hold(MOVE_POLL_S)
            st, t = motor.status(), self.now()
            x = float(prog.aperture(st.position)) if prog.has_motor_axis else math.nan
            self._record(self.rec.append, "motor", t, position=st.position, aperture=x,
                         **self.ctx.late_columns("motor", math.nan))
            self.sup.check_motor(st.position, x if prog.has_motor_axis else self.sup.aperture or 0.0)
            if st.error:
                raise InstrumentStateError("motor", "drive error during the move: "
                                           + (st.error_text or f"code {st.error_code:#06x}"))
            if (miss := self.motion.reading(t, st.position)) is not None:
                raise motion_trip(miss)
            if st.in_target and not st.moving:
                return float(motor.read_position().value)
        motor.stop()
        self.motion.stopped(self.now())
        raise Refused(f"motor did not reach {target * 1e3:.2f} mm in time; stopped")

    def stop_motor(self) -> None:
        self.ctx.motor.stop()
        self.motion.stopped(self.now())

    # ------------------------------------------------------------ monitors, latch, pause
    def read_all(self, due: float = math.nan) -> tuple[dict[str, float], str]:
        """Every channel once through the run's polls (:func:`~bench.runtime.polls.rig_polls`: recorded, supervised,
        the monitors and the encoder verified against what was commanded); ``due``: the run time the reading was
        scheduled for (its lateness is recorded; NaN: on request). Returns the values read (the snapshot's keys:
        voltage, current, displacement, position, aperture, force; a laser reading that is not valid is left out)
        and, for a drive in an error state (recorded; a run would stop here), its own account: the operator reads
        on to see why."""
        self.snapshot.values.clear()
        drive = ""
        for name in ("monitors", "laser", "position", "force", *self.inst.sensors):
            if name not in self._polls:  # no such instrument on this rig
                continue
            try:
                self._polls[name].run(self.ctx, due)
            except InstrumentStateError as exc:
                if name != "position":
                    raise
                drive = exc.detail
        return dict(self.snapshot.values), drive

    def check_monitors(self) -> None:
        """The monitors poll alone (a ramp's check after each set-point)."""
        self._polls["monitors"].run(self.ctx, math.nan)

    def make_safe(self) -> str:
        """After a trip or an error: output zeroed at once, motor stopped, every instrument safe; what was done.

        Where 0 V could not be commanded (the DAQ's or the amplifier's safe state failed: a lost link) the output is
        left to the set-point module's watchdog and the session latches ("output path dead", as a run does), so that
        no set-point goes out until an operator has looked and reset it: :attr:`unproven` holds that trip for the
        session to record. Before, the line said "output zeroed" and the next ``voltage`` energised the rig again
        (found from outside)."""
        self.ctx.v_req = 0.0
        self.inst.cancel.clear()  # after a cancelled wait the safe-state commands must still go out
        try:
            errors = self.inst.safe_state()
        except Exception as exc:  # safe_state reports driver errors; anything else is said, not raised
            errors = [f"output path: {type(exc).__name__}: {exc}"]
        output = [e for e in errors if e.split(":", 1)[0] in ("daq", "amplifier", "output path")]
        motor = [e for e in errors if e.startswith("motor:")]
        done: list[str] = []
        if self.inst.amplifier is not None and output:
            if self.latched is None:
                trip = InterlockTrip("output path dead", f"0 V could not be commanded by the host "
                                     f"({'; '.join(output)}): left to the set-point module's watchdog")
                self.latched, self.latched_at, self.unproven = trip, self.now(), trip
            done.append("0 V NOT commanded (left to the set-point module's watchdog)")
        elif self.inst.amplifier is not None:
            self._output_is(float(self.inst.amplifier.commanded))
            done.append("output zeroed")
        if self.inst.motor is not None:
            self.motion.stopped(self.now())
            done.append("motor NOT stopped" if motor else "motor stopped")
        text = ", ".join(done) or "every instrument to its safe state"
        return text + (f" ({'; '.join(errors)})" if errors else "")

    def latch(self, trip: InterlockTrip) -> str:
        """Latch ``trip``: output to 0 V at once, motor stopped; refused energising until :meth:`reset_latch`."""
        self.latched, self.latched_at = trip, self.now()
        done = self.make_safe()
        self.verifier = self.ctx.verifier = OutputVerifier(self.rig, None)  # counted afresh from the zeroed output
        self.verifier.commanded(self.now(), self.ctx.v_cmd)
        return done

    def latched_before(self, fault: str) -> None:
        """A latch this session found (a run or an earlier session left it): held off as one of its own."""
        self.latched, self.latched_at = InterlockTrip("latched before this session", fault), self.now()

    def reset_latch(self) -> str:
        """Clear the latch; returns the kind of fault it held."""
        if self.latched is None:
            raise Refused("no interlock latched: nothing to reset")
        kind, self.latched = self.latched.kind, None
        return kind

    def pause(self, by: str) -> str:
        """Paused (the run's pause): output ramped to 0 V over ``shutdown_ramp_s``, motor stopped, an event; every
        set-point but 0 V refused until :meth:`resume`."""
        if self.paused:
            raise Refused("already paused")
        self.request_pause(by)
        self.paused, self._paused_at = True, self.now()
        self.pauses += 1
        self.ctx.v_req = 0.0
        self._event("pause", f"paused by {by}: output ramping to 0 V, motor held, recording goes on")  # as a run's
        self._make_paused()
        return f"paused by {by}: {self._zero_seen()}, motor held; `resume` lets high voltage on again"

    def _zero_seen(self) -> str:
        """The paused output as its monitor shows it: read (recorded, supervised, verified) until it is at 0 V, or
        for ``DISCHARGE_WAIT_S`` — the pause said "output 2 V", the set-point, while the next `read` showed 4223 V
        on the discharging output (an outside tester). Also a ``verify`` event, as a run's pause has."""
        if self.inst.amplifier is None:
            return "no amplifier"
        self._wait(self.now() + MONITOR_SETTLE_S)  # fresh conversions at the zeroed output
        deadline = self.now() + DISCHARGE_WAIT_S
        while True:
            self.check_monitors()
            v = self.snapshot.values.get("voltage", math.nan)
            if math.isfinite(v) and abs(v) <= self.safe_v:
                text = f"0 V commanded: the voltage monitor reads {whole(v)} V at {self.now():.3f} s"
                self._event("verify", text)
                return f"output at 0 V ({text})"
            if self.now() >= deadline:
                return (f"0 V commanded, but the voltage monitor still reads {whole(v)} V at {self.now():.3f} s: "
                        "do not touch the specimen")
            self._wait(self.now() + MONITOR_REREAD_S)

    def pause_asked_by(self) -> str:
        """Who asked for the pause that ended a command (a signal, another thread)."""
        return self._paused_wanted()[1] or "a pause request"

    def on_stop_signal(self, reason: str, sig: int) -> None:
        """A stop signal (:func:`~bench.runtime.engine.stop_signals`), as the engine takes it in a run."""
        self._on_signal(reason, sig)

    def resume(self, by: str) -> str:
        if not self.paused:
            raise Refused("not paused: nothing to resume")
        self.request_resume(by)
        self.paused = False
        self._pause_by = self._resume_by = None
        self._event("resume", f"resumed by {by} after {self.now() - self._paused_at:.3f} s paused")
        return f"resumed by {by}"

    # ------------------------------------------------------------ a Ctrl-C, the end
    @property
    def interrupted(self) -> str | None:
        """The Ctrl-C that ended the command under way (not the session), if any."""
        return self._interrupt

    @property
    def stopping(self) -> bool:
        """Whether the engine's stop has begun (nothing may follow its zero)."""
        return self._stopping

    @property
    def stop_reason(self) -> str | None:
        """The stop request that ends the session, if any."""
        return self._stop_reason

    def end_interrupt(self) -> str:
        """The command a Ctrl-C ended: traffic let through again, motor stopped, output held; what was done."""
        reason, self._interrupt = self._interrupt, None
        self.inst.cancel.clear()
        notes = []
        if self.inst.motor is not None:
            try:
                self.stop_motor()
                notes.append("motor stopped")
            except InstrumentError as exc:
                notes.append(f"motor stop failed: {exc}")
        if self.inst.amplifier is not None and self.paused:  # a pause's ramp cut short: 0 V now
            try:
                self.zero()
                notes.append("paused: output 0 V")
            except InstrumentError as exc:
                notes.append(f"0 V not commanded ({exc}); {self.make_safe()}")
        elif self.inst.amplifier is not None:
            self.ctx.v_req = self.ctx.v_cmd  # held (and kept alive) at the last set-point sent
            notes.append(f"output held at {self.ctx.v_req:.0f} V")
        return f"{reason}: command ended" + "".join(f"; {n}" for n in notes)

    def clear_interrupt(self) -> None:
        """A Ctrl-C as the command ended: nothing left to interrupt."""
        if self._interrupt is not None and self._stop_reason is None:
            self._interrupt = None
            self.inst.cancel.clear()

    def urgent(self) -> None:
        """A stop request during the end: the exit ramp is cut short (0 V at once)."""
        self._urgent.set()

    def end(self, state: str, reason: str) -> str:
        """The engine's bounded stop (``_shut_down``), the file left open for the session's last line; returns
        how the output was made safe."""
        return self._shut_down(state, reason, finish=False)
