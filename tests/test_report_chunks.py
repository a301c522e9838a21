"""Analysis, report and inspect read a run file in bounded slices (issue 25 item 5) and open it once (issue 22
item 5), with the results of the whole-file computation.

The chunk size is forced small so that every window, neighbour search and reduction crosses chunk edges; the
reference is the same figure computed on the whole record (chunk larger than the file) or, independently, from the
signal the test wrote (a 7-kV raised cosine and a displacement in phase with V²).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import bench.storage.chunks as chunks
from bench.analysis.applied import applied_voltage, applied_window
from bench.analysis.runs import analyse
from bench.benchmarks.export import RATE_HZ, STEP_S, write_report_run
from bench.storage.chunks import StreamChunks, open_source
from bench.storage.recorder import Column, Recorder
from bench.storage.runfile import open_h5, open_run

STEPS = 2
PER_STEP = int(STEP_S * RATE_HZ)


@pytest.fixture(scope="module")
def steps_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two 10-s raised-cosine steps at 10 kHz (bench benchmark export's report run, short)."""
    path = tmp_path_factory.mktemp("chunks") / "steps.h5"
    write_report_run(path, STEPS)
    return path


def _figures(path: Path) -> list[tuple[str, float, dict[str, float], dict[str, list[float]]]]:
    return [(s.kind, s.voltage, s.figures, s.series) for s in analyse(path).steps]


@pytest.mark.parametrize("which", ["steps", "short"])
def test_figures_of_merit_in_windows_equal_the_whole_file_computation(which: str, request: pytest.FixtureRequest,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    path = request.getfixturevalue("steps_run" if which == "steps" else "short_run")
    monkeypatch.setattr(chunks, "CHUNK_ROWS", 10**9)  # one chunk: every stream read whole
    whole = _figures(path)
    monkeypatch.setattr(chunks, "CHUNK_ROWS", 997)  # windows, neighbours and indexes across chunk edges
    small = _figures(path)
    assert small == whole and whole  # bit for bit: the same samples meet the same arithmetic
    if which == "steps":  # against the signal written: u = 1 mm·(V/7 kV)², V = 3.5 kV·(1 − cos 2πt), 0.5-V noise
        assert len(whole) == STEPS
        for _kind, vpk, figs, series in whole:
            assert vpk == pytest.approx(7000.0, abs=3.0)
            assert figs["peak_first"] == pytest.approx(1e-3, abs=1e-7)
            assert figs["lag_first"] == pytest.approx(0.0, abs=1e-3)  # in phase (noise moves a flat crest)
            assert len(series["peaks"]) == STEP_S * 1.0  # 1 Hz: one peak a cycle


def test_the_applied_voltage_of_a_window_interpolates_as_the_whole_trace(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A software-timed record: sparse set-points with motor-only rows (NaN volts) and no DAQ command."""
    path = tmp_path / "sw.h5"
    streams = {"setpoints": [Column("voltage", "V", ""), Column("aperture", "m", "")],
               "amplifier": [Column("voltage", "V", ""), Column("current", "A", "")]}
    rec = Recorder(path, {"protocol_name": "t"}, streams, [], {"setpoints": 20.0, "amplifier": 5.0})
    t_sp = np.array([0.0, 0.5, 0.5, 1.0, 1.2, 3.0, 3.0, 3.5, 7.0, 9.0])
    v_sp = np.array([0.0, 1e3, np.nan, 2e3, np.nan, np.nan, 4e3, np.nan, 5e3, 0.0])
    rec.append("setpoints", t_sp, voltage=v_sp, aperture=np.zeros(t_sp.size))
    t_amp = np.arange(0.0, 9.0, 0.2)
    rec.append("amplifier", t_amp, voltage=np.sin(t_amp) * 1e3, current=np.zeros(t_amp.size))
    rec.finish("completed", "test")
    whole = applied_voltage(open_run(path), measured=True)
    assert whole.source == "setpoints"  # no DAQ command: the set-points stand for the drive
    monkeypatch.setattr(chunks, "CHUNK_ROWS", 3)
    with open_h5(path) as f:
        streams = StreamChunks(f)
        for t0, t1 in ((0.0, 9.0), (1.1, 2.9), (3.0, 3.0), (3.6, 6.9), (0.5, 0.5), (7.5, 20.0)):
            part = applied_window(streams, t0, t1, measured=True)
            q = np.linspace(t0, t1, 41)
            np.testing.assert_array_equal(np.interp(q, part.t, part.v), np.interp(q, whole.t, whole.v))
            inside = (whole.t >= t0) & (whole.t <= t1)
            np.testing.assert_array_equal(part.v[(part.t >= t0) & (part.t <= t1)], whole.v[inside])


def test_the_report_opens_the_file_once_and_reads_no_slice_longer_than_a_step(steps_run: Path, tmp_path: Path,
                                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    from bench import report as report_module

    monkeypatch.setattr(chunks, "CHUNK_ROWS", 4_096)
    monkeypatch.setattr(report_module, "LOOP_POINTS", 3_000)  # light figures: the reads are what is checked
    monkeypatch.setattr(report_module, "VECTOR_FORMATS", ())
    monkeypatch.setattr(report_module, "DPI", 40)
    reads: list[tuple[str, int]] = []
    real_read = StreamChunks.read

    def spy(self: StreamChunks, stream: str, column: str, a: int, b: int) -> np.ndarray:
        reads.append((stream, max(0, min(b, self.length[stream]) - a)))
        return real_read(self, stream, column, a, b)

    opened: list[str] = []
    real_open = chunks.open_h5

    def counting_open(p: Path):  # type: ignore[no-untyped-def]
        opened.append(str(p))
        return real_open(p)

    def no_whole_read(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("the report read a run whole (open_run)")

    monkeypatch.setattr(StreamChunks, "read", spy)
    monkeypatch.setattr(chunks, "open_h5", counting_open)
    monkeypatch.setattr("bench.storage.runfile.open_run", no_whole_read)
    a, paths = report_module.report(steps_run, tmp_path / "rep")
    assert len(a.steps) == STEPS and [p.name for p in paths] == ["displacement_vs_time.png",
                                                                 "displacement_vs_voltage.png"]
    assert opened == [str(steps_run)]
    longest = max(n for _, n in reads)
    assert {s for s, _ in reads} >= {"laser", "amplifier", "setpoints"}
    # a step's window (100,000 records and the bounding ones) at most; the laser holds 200,000
    assert longest <= PER_STEP + 2 < STEPS * PER_STEP


def test_a_decimated_line_keeps_each_span_s_extremes(steps_run: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(chunks, "CHUNK_ROWS", 7_777)  # spans cross chunk edges
    with open_source(steps_run) as src:
        t, u = src.streams.decimate("laser", "displacement", 5.0, 25.0, spans=300)
        n = src.streams.length["laser"]
        all_t = np.concatenate([c["t"] for c in src.streams.chunks("laser", rows=n)])
        all_u = np.concatenate([c["displacement"] for c in src.streams.chunks("laser", rows=n)])
    keep = (all_t >= 5.0) & (all_t <= 25.0)
    rt, ru = all_t[keep], all_u[keep]
    assert t.size <= 600 and np.all(np.diff(t) > 0)  # in time order, two points a span at most
    _each_span_s_extremes_on_the_line(rt, ru, t, u, 300, (0, 1, 150, 299))


def _each_span_s_extremes_on_the_line(rt: np.ndarray, ru: np.ndarray, t: np.ndarray, u: np.ndarray, spans: int,
                                      which: tuple[int, ...]) -> None:
    """Of the records (rt, ru), each of the ``which`` equal intervals of time has its minimum and maximum on the
    line (t, u), where they were recorded."""
    k_of = np.clip(np.searchsorted(np.linspace(rt[0], rt[-1], spans + 1), rt, side="right") - 1, 0, spans - 1)
    for k in which:
        seg_t, seg_u = rt[k_of == k], ru[k_of == k]
        assert seg_t.size, k
        for i in (int(np.argmin(seg_u)), int(np.argmax(seg_u))):
            assert seg_u[i] in u[t == seg_t[i]], (k, seg_t[i])


def test_a_stream_whose_rate_changes_is_cut_by_time_not_by_record_count(tmp_path: Path) -> None:
    """A drive's 10-kHz readings for 1 s, then a pause's 10-Hz readings for 10 s (last note: the report's figures cut
    a stream into equal runs of records, so the pause's 100 readings fell into one span and drew two points over
    10 s). Cut by time, each of 22 spans (0.5 s) holds its own extremes: the pause keeps its shape."""
    from bench.storage.recorder import Column, Recorder

    path = tmp_path / "paused.h5"
    rec = Recorder(path, {"protocol_name": "rate change"}, {"laser": [Column("displacement", "m", "")]}, [],
                   {"laser": 10_000.0})
    dense = np.arange(10_000) / 10_000.0
    sparse = 1.0 + np.arange(1, 101) / 10.0
    rec.append("laser", dense, displacement=1e-3 * np.sin(2 * np.pi * 5 * dense))
    rec.append("laser", sparse, displacement=1e-3 * np.cos(2 * np.pi * 0.3 * sparse))  # 3 slow periods
    rec.finish("completed", "test")
    with open_source(path) as src:
        t, u = src.streams.decimate("laser", "displacement", 0.0, 11.0, spans=22)
    rt, ru = np.concatenate([dense, sparse]), np.concatenate([1e-3 * np.sin(2 * np.pi * 5 * dense),
                                                               1e-3 * np.cos(2 * np.pi * 0.3 * sparse)])
    assert np.all(np.diff(t) > 0) and t.size <= 44
    assert (t > 1.0).sum() >= 36  # the pause: two points in each of its 20 spans (one record may be both)
    _each_span_s_extremes_on_the_line(rt, ru, t, u, 22, tuple(range(22)))
