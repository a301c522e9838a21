"""Issue 22 item 2: every instrument a run reads is a bluesky-style ``Readable`` — ``read()`` keyed exactly as
``describe()`` — so the run time records them all with one generic poll, and a new instrument is added to a rig
without any engine change (the worked example of docs/architecture.md)."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import bench.runtime.run as run_module
import drivers
from bench.rig import load_rig
from bench.runtime.instruments import Instruments, build_instruments
from bench.storage.runfile import open_run
from drivers.interfaces import (
    CheckResult,
    ClockFn,
    DataKey,
    Identity,
    Readable,
    Reading,
    Sensor,
    StreamDescription,
)
from tests.conftest import ROOT, start_rig

RIGS = ("thesis-sim", "lsdea-motor-sim", "thesis-daq-sim", "lsdea-motor-daq-sim")  # between them, every Readable
# driver class (the last: the load cell's bridge amplifier on a T7 input)


def _readable_driver_classes() -> set[type]:
    """Every class of the drivers package that has both ``describe`` and ``read`` (the Readable contract)."""
    found: set[type] = set()
    for mod in pkgutil.walk_packages(drivers.__path__, "drivers."):
        for _, cls in inspect.getmembers(importlib.import_module(mod.name), inspect.isclass):
            if cls.__module__ == mod.name and not getattr(cls, "_is_protocol", False) \
                    and callable(getattr(cls, "describe", None)) and callable(getattr(cls, "read", None)):
                found.add(cls)
    return found


@pytest.fixture(scope="module", params=RIGS)
def rig_instruments(request: pytest.FixtureRequest) -> Iterator[Instruments]:
    """The drivers of a simulated rig, connected to their twins on served ports (virtual clock)."""
    r = start_rig(request.param)
    yield r.inst
    r.inst.close()
    r.sim.stop()


def test_read_is_keyed_exactly_as_describe(rig_instruments: Instruments) -> None:
    """One reading per described column, no other key; each in the column's unit; flags 0 or 1; the stream named
    after the role (the recorder's layout comes from the same describe())."""
    roles = list(rig_instruments.readables())
    assert roles
    for role, drv in roles:
        d = drv.describe()
        r = drv.read()
        assert d.stream == role
        assert set(r) == {k.name for k in d.columns}, (role, set(r))
        for key in d.columns:
            assert isinstance(r[key.name], Reading)
            assert r[key.name].unit == key.unit, (role, key.name)
            if np.dtype(key.dtype).kind in "ub":
                assert r[key.name].value in (0.0, 1.0), (role, key.name)


def test_the_rigs_read_above_carry_every_readable_driver_class() -> None:
    """The contract test reads every Readable driver class from its twin (a new driver joins a rig in RIGS)."""
    built = {type(drv) for name in RIGS
             for _, drv in build_instruments(load_rig(ROOT / "rigs" / f"{name}.toml")).readables()}
    found = _readable_driver_classes()
    assert len(found) >= 5 and found <= built, found - built


# ------------------------------------------------------------ the worked example: adding an instrument
START_K = 296.15  # what the fake thermometer reads first [K]
STEP_K = 0.25  # and how much more at each read after


class Thermometer:
    """A thermometer the run time has never heard of: the Instrument and Readable contracts, nothing else."""

    name = "thermometer"

    def __init__(self, clock: ClockFn) -> None:
        self.clock = clock
        self.reads = 0

    def describe(self) -> StreamDescription:
        return StreamDescription("thermometer", (DataKey("temperature", "K", "specimen surface temperature"),),
                                 "fake thermometer (tests/test_readable.py)")

    def read(self) -> dict[str, Reading]:
        value = START_K + STEP_K * self.reads
        self.reads += 1
        return {"temperature": Reading(value, "K", self.clock())}

    def connect(self) -> None:
        pass

    def close(self) -> None:
        pass

    def identify(self) -> Identity:
        return Identity("test", "thermometer")

    def safe_state(self) -> None:
        pass

    def check(self) -> CheckResult:
        return CheckResult("ok", (("temperature", self.read()["temperature"]),))


PROTOCOL = f"""
[protocol]
name = "thermometer-example"
rig = "{ROOT / 'rigs' / 'thesis-sim.toml'}"

[recording]
monitors_Hz = 5

[[steps]]
type = "relax"
name = "rest"
duration_s = 3.0
"""


def test_a_new_instrument_is_recorded_to_its_own_stream_without_an_engine_change(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A thermometer put on the thesis rig's instruments (as a rig-file section's builder would) is read by the
    generic poll every SENSOR_PERIOD_S (1 s: polls.py declares no hooks for the role) over a 3 s step — at run
    time 0, 1 and 2 s — and its values land, in order and with their unit, in a stream of its own."""
    from bench.runtime.polls import SENSOR_PERIOD_S
    from bench.runtime.run import execute, plan_run

    built = run_module.build_instruments

    def with_thermometer(*args: Any, **kwargs: Any) -> Instruments:
        inst = built(*args, **kwargs)
        thermometer = Thermometer(kwargs["clock"])
        assert isinstance(thermometer, Sensor) and isinstance(thermometer, Readable)
        inst.sensors["thermometer"] = thermometer
        return inst

    monkeypatch.setattr(run_module, "build_instruments", with_thermometer)
    path = tmp_path / "thermometer-example.toml"
    path.write_text(PROTOCOL, encoding="utf-8")
    result = execute(plan_run(path), tmp_path / "run.h5", virtual=True)
    assert result.state == "completed", result.reason
    s = open_run(result.path).streams["thermometer"]
    assert s.units["temperature"] == "K" and s.rate == 1 / SENSOR_PERIOD_S
    n = round(3.0 / SENSOR_PERIOD_S)  # polls at 0, 1, 2 s; none at the step's end
    assert s.columns["temperature"].tolist() == [START_K + STEP_K * k for k in range(n)]
    assert np.allclose(s.t, np.arange(n) * SENSOR_PERIOD_S, atol=0.05)  # on the run clock, stamped by the reading
    assert np.all(s.columns["late"] >= 0)  # the generic poll's lateness column, as every software-timed stream


def test_a_step_s_poll_asks_describe_once_and_records_every_read_to_its_stream() -> None:
    """The generic poll of one step asks the instrument's describe() once, at its first poll, not at each of its
    reads (a 20-Hz encoder poll would build the same description 20 times a second); every read still lands in the
    stream it names, stamped with the reading's time on the run clock and its lateness."""
    import contextlib
    from types import SimpleNamespace

    from bench.runtime.polls import Polled, _role_poll, _sensor_period

    described = 0

    class Counted(Thermometer):
        def describe(self) -> StreamDescription:
            nonlocal described
            described += 1
            return super().describe()

    rows: list[tuple[Any, ...]] = []
    e = SimpleNamespace(t0=10.0, rec=SimpleNamespace(append=lambda *a, **k: rows.append((*a, k))),
                        late_columns=lambda stream, late: {"late": late}, lateness=lambda due: 0.5 - due,
                        offset=0.0, waiting_on=lambda role, due: contextlib.nullcontext())
    clock = iter([11.0, 12.0, 13.0])
    poll = _role_poll("thermometer", Counted(lambda: next(clock)), Polled("thermometer", _sensor_period))
    for due in (0.0, 0.1, 0.2):
        poll.run(e, due)  # type: ignore[arg-type]  # the context's parts a poll uses
    assert described == 1
    assert rows == [("thermometer", t - 10.0, {"temperature": START_K + STEP_K * k, "late": 0.5 - due})
                    for k, (t, due) in enumerate(((11.0, 0.0), (12.0, 0.1), (13.0, 0.2)))]
