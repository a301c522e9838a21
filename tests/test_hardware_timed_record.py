"""What a hardware-timed collect records from one block of scans: the output commanded at each scan (the values
kept, the first or last of them beyond), the per-scan validity of a block with an invalid sample, and what the
supervisor and the verifier are given (peaks and last values over the valid scans only)."""

from __future__ import annotations

import types
from typing import Any

import numpy as np

from bench.rig import load_rig
from bench.runtime.hardware_timed import HardwareTimed
from drivers.interfaces import StreamBlock
from tests.conftest import ROOT


class _Rec:
    def __init__(self) -> None:
        self.rows: dict[str, dict[str, np.ndarray]] = {}

    def append(self, stream: str, t: np.ndarray, **columns: np.ndarray) -> None:
        self.rows[stream] = {"t": t, **columns}  # as given: the recorder queues the arrays themselves


class _Sup:
    def __init__(self) -> None:
        self.monitors: list[tuple[float, float]] = []
        self.forces: list[float] = []

    def check_monitors(self, volts: float, amps: float) -> None:
        self.monitors.append((volts, amps))

    def check_force(self, newtons: float) -> None:
        self.forces.append(newtons)


class _Verifier:
    def __init__(self) -> None:
        self.calls: list[tuple[np.ndarray, ...]] = []

    def scans(self, t: np.ndarray, v: np.ndarray, commanded: np.ndarray, ok: np.ndarray) -> None:
        self.calls.append((np.array(t), np.array(v), np.array(commanded), np.array(ok)))


class _Amp:
    @staticmethod
    def monitor_values(vmon: np.ndarray, imon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return vmon * 1000.0, imon * 0.5


def _hw(received: int) -> tuple[HardwareTimed, Any]:
    """A DAQ side on the motor rig (vmon, imon, force on the scan clock) with scans 50 … 149 kept: 0, 10, … 990 V."""
    ctx = types.SimpleNamespace(rec=_Rec(), snapshot=types.SimpleNamespace(values={}), sup=_Sup(),
                                verifier=_Verifier(), t0=2.0, v_cmd=0.0)
    daq = types.SimpleNamespace(scans_received=received)
    hw = HardwareTimed(load_rig(ROOT / "rigs" / "lsdea-motor-daq-sim.toml"), daq, _Amp(), ctx)  # type: ignore[arg-type]
    hw._commanded, hw._base = np.arange(100) * 10.0, 50
    return hw, ctx


def _block(first: int, volts: list[list[float]], valid: list[list[bool]] | None = None) -> StreamBlock:
    v = np.array(volts, dtype=float)
    ok = np.ones(v.shape, bool) if valid is None else np.array(valid)
    return StreamBlock(first, 2.5, 0.5, ("vmon", "imon", "force"), v, ok)


def test_the_commanded_column_holds_the_value_of_each_scan_and_the_kept_ends_beyond_them() -> None:
    cases = [(60, [100.0, 110.0, 120.0, 130.0]),  # scans 60 … 63: kept values 10 … 13
             (148, [980.0, 990.0, 990.0, 990.0]),  # 148, 149 kept; 150, 151 beyond the last: its value
             (48, [0.0, 0.0, 0.0, 10.0])]  # 48, 49 before the first kept: its value
    for first, want in cases:
        hw, ctx = _hw(first + 4)
        hw._record(_block(first, [[1.0, 1.0, 0.5]] * 4))
        cmd = ctx.rec.rows["amplifier"]["commanded"]
        assert cmd.tolist() == want
        assert ctx.verifier.calls[0][2].tolist() == want
        assert ctx.rec.rows["amplifier"]["t"].tolist() == [2.5 + 0.5 * (first + k) - 2.0 for k in range(4)]
        hw._commanded[:] = -1.0  # what was recorded is its own, not a view of the values kept
        assert ctx.rec.rows["amplifier"]["commanded"].tolist() == want


def test_a_scan_with_an_invalid_sample_is_invalid_and_left_out_of_the_checks() -> None:
    hw, ctx = _hw(64)
    volts = [[1.0, 2.0, 0.5], [-7.0, 9.0, -8.0], [3.0, -4.0, 2.0], [0.5, 0.5, 0.25]]
    valid = [[True] * 3, [True, False, True], [True] * 3, [False, True, True]]
    hw._record(_block(60, volts, valid))
    assert ctx.rec.rows["load_cell"]["ok"].tolist() == [1, 0, 1, 0]
    assert ctx.sup.monitors == [(3000.0, -2.0)]  # the peaks of scans 60 and 62: the invalid ones are left out
    assert ctx.sup.forces == [2.0]
    assert ctx.snapshot.values["voltage"] == 3000.0 and ctx.snapshot.values["force"] == 2.0  # the last valid scan
    assert ctx.verifier.calls[0][3].tolist() == [True, False, True, False]


def test_a_block_of_valid_scans_is_checked_whole() -> None:
    hw, ctx = _hw(64)
    hw._record(_block(60, [[1.0, 2.0, 0.5], [-7.0, 9.0, -8.0], [3.0, -4.0, 2.0], [0.5, 0.5, 0.25]]))
    assert ctx.rec.rows["load_cell"]["ok"].tolist() == [1, 1, 1, 1]
    assert ctx.sup.monitors == [(-7000.0, 4.5)] and ctx.sup.forces == [-8.0]
    assert ctx.snapshot.values["voltage"] == 500.0 and ctx.snapshot.values["force"] == 0.25
    assert ctx.verifier.calls[0][3].tolist() == [True] * 4


def test_a_block_without_a_valid_scan_records_it_and_checks_nothing() -> None:
    hw, ctx = _hw(62)
    hw._record(_block(60, [[1.0, 2.0, 0.5], [3.0, 4.0, 5.0]], [[False, True, True], [True, True, False]]))
    assert ctx.rec.rows["load_cell"]["ok"].tolist() == [0, 0]
    assert ctx.sup.monitors == [] and ctx.verifier.calls == [] and "voltage" not in ctx.snapshot.values
