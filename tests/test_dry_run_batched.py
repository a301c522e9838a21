"""The dry run applies a segment's ticks at once (:func:`bench.protocol.tick_arrays.tick_arrays`, the compiled
go-to chain, :meth:`Plant.add_motions`); the reference here is what it did before, tick by tick through
:func:`~bench.protocol.program.ticks`, ``set_amplifier_input`` and ``set_motion``: the same ticks, and a plant
whose every block is the same, bit for bit."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench.core.clock import VirtualClock
from bench.core.motion import MotionProfile
from bench.core.plant import Plant, PlantBlock
from bench.protocol.predict import Prediction, _apply_ticks, build_plant
from bench.protocol.program import Program, Segment, change_specimen, compile_program, ticks
from bench.protocol.schema import load_protocol
from bench.protocol.tick_arrays import tick_arrays
from bench.runtime.run import resolve_rig
from tests.conftest import RIGS, ROOT

SHORT = ROOT / "protocols" / "short"
CASES = [(SHORT / "lsdea-isopotential-short.toml", None), (SHORT / "lsdea-isopotential-short.toml", "lsdea-motor-sim"),
         (SHORT / "lsdea-isometric-short.toml", "lsdea-motor-sim"), (SHORT / "thesis-sweeps-short.toml", "thesis-sim")]


def _program(path: Path, rig: str | None) -> Program:
    protocol = load_protocol(path)
    return compile_program(protocol, resolve_rig(protocol, None if rig is None else RIGS / f"{rig}.toml"))


def _bits(a: np.ndarray | list[float]) -> bytes:
    return np.ascontiguousarray(a, dtype=float).tobytes()


@pytest.mark.parametrize(("path", "rig"), CASES, ids=lambda c: getattr(c, "stem", str(c)))
def test_tick_arrays_are_the_ticks(path: Path, rig: str | None) -> None:
    program = _program(path, rig)
    for seg in program.segments:
        ref = list(ticks(program, seg))
        tab = tick_arrays(program, seg)
        assert _bits([k.t for k in ref]) == _bits(tab.t)
        volts = [k.voltage for k in ref]
        assert (tab.voltage is None) == (seg.voltage is None or not ref)
        if tab.voltage is not None:
            assert _bits([math.nan if v is None else v for v in volts]) == _bits(tab.voltage)
        motor = [(i, k.motor) for i, k in enumerate(ref) if k.motor is not None]
        assert [i for i, _ in motor] == tab.motor.tolist()
        for col, arr in enumerate((tab.target, tab.velocity, tab.acceleration)):
            assert _bits([m[col] for _, m in motor]) == _bits(arr)


def _tick_by_tick(program: Program, seg: Segment, plant: Plant, clock: VirtualClock, gain: float, played: bool,
                  seen: list[float]) -> None:
    """The former dry run's loop over one segment's ticks; ``seen``: [peak |voltage|, lowest, highest motor target]
    so far, updated as that loop did."""
    for tick in ticks(program, seg):
        v = None if played else tick.voltage
        if v is None and tick.motor is None:
            continue
        clock.advance_to(tick.t)
        if v is not None:
            seen[0] = max(seen[0], abs(v))
            plant.set_amplifier_input(v / gain)
        if tick.motor is not None:
            target, vel, acc = tick.motor
            seen[1], seen[2] = min(seen[1], target), max(seen[2], target)

            def plan(t0: float, p: float, vv: float, tg: float = target, ve: float = vel,
                     ac: float = acc) -> MotionProfile:
                return MotionProfile.plan(t0, p, vv, tg, ve, ac, ac)

            plant.set_motion(plan)


@pytest.mark.parametrize(("path", "rig"), CASES, ids=lambda c: getattr(c, "stem", str(c)))
def test_a_segment_at_once_drives_the_plant_as_tick_by_tick(path: Path, rig: str | None) -> None:
    program = _program(path, rig)
    runs = []
    for batched in (False, True):
        seen = [0.0, math.inf, -math.inf]  # peak |voltage|, motor range: what the dry run reports
        clock = VirtualClock()
        plant = build_plant(program, clock)
        blocks: list[PlantBlock] = []
        plant.listeners.append(blocks.append)
        played = program.rig.amplifier is not None and program.rig.amplifier.drive == "daq"
        for seg in program.segments:
            if seg.changes:
                change_specimen(plant, seg.changes)
            seg_played = played and seg.voltage is not None and seg.duration > 0
            if seg_played and not program.has_motor_axis:
                continue
            if batched:
                peaks = None if seg_played else Prediction(0.0, {}, 0, peak_voltage=seen[0])
                lo, hi = _apply_ticks(program, seg, plant, clock, plant.hv.gain, peaks)
                seen[1], seen[2] = min(seen[1], lo), max(seen[2], hi)
                if peaks is not None:
                    seen[0] = peaks.peak_voltage
            else:
                _tick_by_tick(program, seg, plant, clock, plant.hv.gain, seg_played, seen)
            clock.advance_to(seg.t_end)
            plant.advance_to(seg.t_end)
        runs.append((blocks, plant.motion, clock.now(), seen))
    (ref, ref_motion, ref_now, ref_seen), (got, got_motion, got_now, got_seen) = runs
    assert len(ref) == len(got) > 0 and ref_now == got_now
    assert _bits(ref_seen) == _bits(got_seen)  # the peak voltage and the motor range the dry run reports
    for a, b in zip(ref, got, strict=True):
        for f in ("t", "voltage", "current", "displacement", "force", "field", "breakdown", "v_out", "i_out"):
            assert _bits(getattr(a, f)) == _bits(getattr(b, f)), f
    for f in ("t_start", "p_start", "v_start", "acc"):
        assert _bits(getattr(ref_motion, f)) == _bits(getattr(got_motion, f))

