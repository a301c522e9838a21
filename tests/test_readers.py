"""Run files in the ecosystem's conventions: xarray (h5netcdf and netCDF4 engines), h5dump and silx read a real
run file; time bases are dimension scales (a group's coordinate ``t``); every numeric dataset has units; strings
are declared UTF-8; bench's readers still read a file during the run (SWMR) and files of format 1.

References come from outside the code under test: the rig file's scan rate, the protocol's step names, and the
time base as plain h5py reads it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from datetime import datetime
from pathlib import Path

import h5py
import numpy as np
import pytest
import silx.io
import xarray as xr

from bench.identify.core import FitResult
from bench.identify.store import write_fit
from bench.rig import load_rig
from bench.runtime.run import execute, plan_run
from bench.storage.recover import recover
from bench.storage.runfile import open_run
from tests.conftest import RIGS, ROOT

RIG = RIGS / "thesis-daq-sim.toml"  # hardware-timed: every analog channel on one scan clock
STEP = "Dehnung µ-Schritt"  # a non-ASCII step name
ENGINES = ["h5netcdf", "netcdf4"]

PROTOCOL = f"""
[protocol]
name = "readers"
description = "Two short steps for the reader tests"
rig = "{RIG.as_posix()}"

[specimen]
temperature_K = 296.0

[recording]
monitors_Hz = 5
setpoint_Hz = 50

[[steps]]
type = "waveform"
name = "{STEP}"
channel = "voltage"
kind = "sine"
amplitude = "1 kV"
frequency_Hz = 2.0
cycles = 2

[[steps]]
type = "relax"
name = "Ruhe"
duration_s = 0.5
"""


@pytest.fixture(scope="module")
def run_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed virtual-time run on the simulated LabJack rig (1.5 s of protocol)."""
    folder = tmp_path_factory.mktemp("readers")
    protocol = folder / "readers.toml"
    protocol.write_text(PROTOCOL, encoding="utf-8")
    result = execute(plan_run(protocol), folder / "readers.h5", virtual=True)
    assert result.state == "completed"
    return Path(result.path)


def _streams(path: Path) -> dict[str, np.ndarray]:
    """Stream name → its time base, as plain h5py reads the file."""
    with h5py.File(path, "r") as f:
        return {name: f[name]["t"][:] for name in f if name not in ("status", "events", "program", "fit", "entry")}


def _text(values: np.ndarray) -> list[str]:
    """Strings as xarray returns them: str (netCDF4) or UTF-8 bytes (h5netcdf, fixed-length strings)."""
    return [v.decode() if isinstance(v, bytes) else str(v) for v in values]


@pytest.mark.parametrize("engine", ENGINES)
def test_xarray_sees_each_time_base_as_the_coordinate_of_its_stream(run_path: Path, engine: str) -> None:
    streams = _streams(run_path)
    assert {"setpoints", "amplifier", "laser"} <= set(streams)
    for name, t in streams.items():
        with xr.open_dataset(run_path, engine=engine, group=name, decode_times=False) as ds:
            assert list(ds.dims) == ["t"], (name, ds.dims)  # one dimension: no phony_dim_*
            assert "t" in ds.indexes and ds["t"].attrs["units"].startswith("seconds since ")  # CF: time from the start
            np.testing.assert_array_equal(ds["t"].values, t)
            for var in ds.data_vars.values():
                assert var.dims == ("t",) and var.attrs["units"], (name, var.name)
    rate = load_rig(RIG).daq.scan_rate_Hz
    with xr.open_dataset(run_path, engine=engine, group="laser", decode_times=False) as ds:
        assert ds["displacement"].attrs["units"] == "m"
        ticks = ds["t"].values * rate
    np.testing.assert_allclose(ticks, np.round(ticks), rtol=0, atol=1e-6)  # every sample on the rig's scan clock
    steps = np.diff(np.round(ticks))
    assert steps.min() == 1 and (steps > 1).sum() <= 1  # none lost or doubled (the stream may re-arm once per step)
    packet = 512 // 3  # scans: a step ends with the stream packet that holds its end (3 inputs a scan)
    end = 1.5 * rate  # the protocol's 1.5 s, in scans
    assert ticks[0] == pytest.approx(1) and end <= ticks[-1] <= end + 2 * packet


@pytest.mark.parametrize("engine", ENGINES)
def test_xarray_reads_program_and_events_with_utf8_text(run_path: Path, engine: str) -> None:
    with xr.open_dataset(run_path, engine=engine, group="program") as prog:
        assert list(prog.dims) == ["index"]
        assert _text(prog["name"].values) == [STEP, "Ruhe"]
        np.testing.assert_allclose(prog["duration"].values, [1.0, 0.5])  # 2 cycles at 2 Hz; the relax step
        assert prog["t_start"].attrs["units"] == "s" and prog["duration"].attrs["units"] == "s"
    with xr.open_dataset(run_path, engine=engine, group="events", decode_times=False) as ev:
        assert list(ev.dims) == ["t"] and ev["t"].attrs["units"].startswith("seconds since ")
        kinds, texts = _text(ev["kind"].values), _text(ev["text"].values)
        starts = [text for kind, text in zip(kinds, texts, strict=True) if kind == "start"]
        assert [s.split(" | ")[0] for s in starts] == [STEP, "Ruhe"]
        assert ev["t"].values[kinds.index("end")] == pytest.approx(1.0, abs=0.02)


def test_non_ascii_names_round_trip_and_every_string_is_declared_utf8(run_path: Path) -> None:
    run = open_run(run_path)
    assert [row["name"].decode() for row in run.program] == [STEP, "Ruhe"]
    assert (0.0, 0, "start", f"{STEP} | steps[0]({STEP})") in run.event_list()
    strings: list[str] = []

    def check(name: str, obj: object) -> None:
        if isinstance(obj, h5py.Dataset) and h5py.check_string_dtype(obj.dtype) is not None:
            strings.append(name)
            assert h5py.check_string_dtype(obj.dtype).encoding == "utf-8", name

    with h5py.File(run_path, "r") as f:
        f.visititems(check)
        assert f["program/name"][0].decode("utf-8") == STEP
    assert {"program/name", "events/text", "events/kind", "status/state", "status/reason"} <= set(strings)


def _fit() -> FitResult:
    """A two-parameter fit result (values made up: only its storage is under test)."""
    return FitResult(["mu0", "J0"], ["Pa", "1"], np.array([1e5, 20.0]), np.array([1e4, 2.0]),
                     np.array([1e6, 200.0]), 0.1, "rms", 0.01, 100, 50, 5, 0.5, np.array([0.3, 0.2]),
                     np.eye(2), np.array([0.01, 0.02]))


def test_every_numeric_dataset_has_units_also_status_and_fits(run_path: Path, tmp_path: Path) -> None:
    path = Path(shutil.copy(run_path, tmp_path / "fitted.h5"))
    write_fit(path, "membrane", _fit(), [str(path)])
    numeric: dict[str, object] = {}

    def collect(name: str, obj: object) -> None:
        if isinstance(obj, h5py.Dataset) and obj.dtype.kind in "iufb":
            numeric[name] = obj.attrs.get("units")

    with h5py.File(path, "r") as f:
        f.visititems(collect)
    assert not [name for name, units in numeric.items() if units is None]
    assert numeric["status/updated"] == "s" and numeric["status/samples"] == "1"
    assert numeric["events/step"] == "1" and numeric["program/t_start"] == "s"
    assert str(numeric["laser/t"]).startswith("seconds since ")  # CF time: the run clock from the run's start
    assert list(numeric["fit/membrane-1/values"]) == ["Pa", "1"]  # one unit per parameter
    assert numeric["fit/membrane-1/correlation"] == "1"
    assert numeric["amplifier/voltage"] == "V" and numeric["amplifier/current"] == "A"


@pytest.mark.skipif(shutil.which("h5dump") is None, reason="h5dump not installed (.ci/run installs hdf5-tools)")
def test_h5dump_reads_the_whole_file(run_path: Path) -> None:
    dump = subprocess.run(["h5dump", str(run_path)], capture_output=True, text=True, timeout=120)
    assert dump.returncode == 0, dump.stderr[-2000:]
    assert "h5dump error" not in dump.stderr
    name = subprocess.run(["h5dump", "-d", "/program/name", str(run_path)], capture_output=True, text=True,
                          timeout=60)
    assert name.returncode == 0 and "H5T_CSET_UTF8" in name.stdout, name.stdout + name.stderr
    scale = subprocess.run(["h5dump", "-A", "-d", "/laser/displacement", str(run_path)], capture_output=True,
                           text=True, timeout=60)
    assert scale.returncode == 0 and '"/laser/t"' in scale.stdout  # DIMENSION_LIST points at the time base


def test_silx_opens_the_file(run_path: Path) -> None:
    expected = _streams(run_path)["laser"]
    with silx.io.open(str(run_path)) as f:
        np.testing.assert_array_equal(f["laser/t"][()], expected)
        assert f["laser/displacement"].attrs["units"] == "m"
        assert f["program/name"][0].decode() == STEP


@pytest.mark.parametrize("engine", ENGINES)
def test_xarray_decodes_each_time_base_to_absolute_times_from_the_run_s_start(run_path: Path, engine: str) -> None:
    with h5py.File(run_path, "r") as f:  # the reference: the start as the file's attribute and plain h5py read it
        start = np.datetime64(datetime.fromisoformat(f.attrs["start_time"]).replace(tzinfo=None), "ns")
        t = f["laser/t"][:]
    with xr.open_dataset(run_path, engine=engine, group="laser") as ds:
        assert ds["t"].dtype.kind == "M"  # decoded: datetime64
        expected = start + (t * 1e9).round().astype("timedelta64[ns]")
        assert np.abs(ds["t"].values - expected).max() <= np.timedelta64(1, "us")
        valid = ds["valid"].attrs
        assert valid["flag_meanings"] == "invalid valid" and list(valid["flag_values"]) == [0, 1]
        assert ds["displacement"].attrs["long_name"]


def test_nexus_readers_find_the_default_plot(run_path: Path) -> None:
    from nexusformat.nexus import nxload
    from silx.io.nxdata import get_default

    root = nxload(str(run_path))
    data = root.plottable_data  # followed from the root's default, as NeXus viewers do
    assert data is not None and data.nxclass == "NXdata" and data.nxsignal.nxname == "displacement"
    assert data.nxaxes[0].nxname == "t"
    with silx.io.open(str(run_path)) as f:
        nxdata = get_default(f)
        assert nxdata is not None and nxdata.is_valid and nxdata.signal.name.endswith("/laser/displacement")
        np.testing.assert_array_equal(nxdata.axes[0][()], _streams(run_path)["laser"])
    with h5py.File(run_path, "r") as f:
        assert f.attrs["Conventions"] == "CF-1.10" and f.attrs["NX_class"] == "NXroot"
        assert {"setpoints", "amplifier", "laser"} <= set(f["entry"])


RATE = 1000.0  # Hz: the live writer stamps sample k at k / RATE s
LIVE_WRITER = textwrap.dedent(f"""
    import sys, time
    from pathlib import Path
    import numpy as np
    from bench.storage.recorder import Column, Recorder
    rec = Recorder(Path(sys.argv[1]), {{"protocol_name": "live"}}, {{"laser": [Column("displacement", "m", "")]}},
                   [(0, {STEP!r}, {STEP!r}, "hold", 0.0, 60.0)], {{"laser": {RATE}}})
    rec.event(0.0, 0, "start", {STEP!r})
    for block in range(600):
        t = (block * 100 + np.arange(100)) / {RATE}
        rec.append("laser", t, displacement=t * 1e-3)
        rec.flush()
        if block == 0:
            print("ready", flush=True)
        time.sleep(0.1)
""")


def test_readers_during_a_run(tmp_path: Path) -> None:
    """While the recorder writes (SWMR): bench's reader, and xarray given an h5py SWMR handle; h5dump refuses."""
    path = tmp_path / "live.h5"
    proc = subprocess.Popen([sys.executable, "-c", LIVE_WRITER, str(path)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready", proc.stderr
        first = open_run(path)
        assert first.state == "running" and not first.complete
        assert first.event_list() == [(0.0, 0, "start", STEP)]
        time.sleep(0.6)
        with h5py.File(path, "r", libver="latest", swmr=True) as f:
            with xr.open_dataset(f, engine="h5netcdf", group="laser") as ds:
                t = ds["t"].values
        assert t.size > len(first.streams["laser"])  # more records arrived meanwhile, and xarray sees them
        np.testing.assert_array_equal(t, np.arange(t.size) / RATE)
        if shutil.which("h5dump") is not None:  # no SWMR reader: the writer's mark makes it refuse the file
            assert subprocess.run(["h5dump", "-H", str(path)], capture_output=True, timeout=60).returncode != 0
    finally:
        proc.kill()
        proc.wait(timeout=10)


def _format_1_file(path: Path) -> None:
    """The file of a crashed run as format 1 wrote it: /program and /events as compound datasets, plain time bases,
    one event record beyond the confirmed count."""
    events = np.array([(0.0, 0, b"start", "Schritt µ".encode()), (1.0, 0, b"end", b"x"), (0.0, 0, b"", b"")],
                      dtype=[("t", "f8"), ("step", "i4"), ("kind", "S16"), ("text", "S200")])
    program = np.array([(0, b"steps[0](a)", b"a", b"hold", 0.0, 1.0)],
                       dtype=[("index", "i4"), ("label", "S240"), ("name", "S120"), ("kind", "S16"),
                              ("t_start", "f8"), ("duration", "f8")])
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "dea-bench run 1"
        for name, value in (("state", b"running"), ("reason", b""), ("end_time", b"")):
            f.create_dataset(f"status/{name}", data=np.array([value], dtype="S40"))
        f["status/updated"] = np.array([1.0])
        f["status/samples"] = np.array([3, 2])  # the third event record was never confirmed
        f["status/samples"].attrs["names"] = json.dumps(["laser", "events"])
        f["program"] = program
        f.create_dataset("events", data=events, maxshape=(None,), chunks=(256,))
        f["laser/t"] = np.arange(3) / 10.0
        f["laser/displacement"] = np.arange(3) * 1e-3
        for d in f["laser"].values():
            d.attrs["units"] = "s" if d.name.endswith("/t") else "m"


def test_format_1_files_still_read_and_recover(tmp_path: Path) -> None:
    path = tmp_path / "old.h5"
    _format_1_file(path)
    run = open_run(path)
    assert not run.complete and run.event_list() == [(0.0, 0, "start", "Schritt µ"), (1.0, 0, "end", "x")]
    assert [row["name"].decode() for row in run.program] == ["a"] and float(run.program[0]["duration"]) == 1.0
    np.testing.assert_array_equal(run.streams["laser"].t, [0.0, 0.1, 0.2])
    report = recover(path)
    assert "events: 1 unconfirmed record cut" in report.actions and report.samples == {"laser": 3}
    with h5py.File(path, "r") as f:
        assert f["events"].shape == (2,) and f["events"][1]["kind"] == b"end"


def test_a_file_a_crash_left_open_is_inspected_without_a_fits_error(tmp_path: Path) -> None:
    """A writer killed mid-run leaves HDF5's "open for write" marks: the readers open it as an SWMR reader, and the
    fits (none yet) are read the same way — before, `bench inspect` said "fits not read: Unable to synchronously
    open file (file is already open for write …)" beside a run it had just read."""
    from bench.app.runs import inspect_run

    path = tmp_path / "killed.h5"
    code = textwrap.dedent(f"""
        import os
        import numpy as np
        from bench.storage.recorder import Column, Recorder
        rec = Recorder({str(path)!r}, {{"protocol_name": "p", "rig_name": "r"}},
                       {{"amplifier": [Column("voltage", "V", "")]}}, [], {{"amplifier": 10.0}})
        rec.append("amplifier", np.arange(5) / 10.0, voltage=np.ones(5))
        rec.flush()
        os._exit(0)  # no close: the marks stay, as after kill -9
    """)
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True, timeout=120)
    with pytest.raises(OSError, match="already open for write"):  # the marks are there: plain h5py refuses it
        h5py.File(path, "r")
    found = inspect_run(path)
    assert found.run.state == "running" and found.streams["amplifier"].samples == 5
    assert found.fits == [] and found.fits_error == ""
