"""bench plot: a quick-look figure of any streams; the envelope keeps every extreme of the record (checked against
the file as plain h5py reads it), units on every axis, one line of error for a stream the file lacks."""

from __future__ import annotations

import errno
import itertools
import json
import re
from pathlib import Path

import h5py
import matplotlib
import numpy as np
import pytest
from typer.testing import CliRunner

from bench.analysis.quicklook import envelopes
from bench.cli import app

matplotlib.use("Agg")


@pytest.fixture
def run_file(short_run: Path) -> Path:
    return short_run


def _plain(path: Path, stream: str, column: str) -> np.ndarray:
    with h5py.File(path, "r") as f:
        n = int(dict(zip(json.loads(f["status/samples"].attrs["names"]), f["status/samples"][:], strict=True))[stream])
        return f[f"{stream}/{column}"][:n]


def test_the_envelope_keeps_every_extreme_and_reads_in_chunks(run_file: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import bench.storage.chunks as chunks

    monkeypatch.setattr(chunks, "CHUNK_ROWS", 7_777)  # bins cross chunk edges
    (env,) = [e for e in envelopes(run_file, ["laser"], columns=300) if e.column == "displacement"]
    u, t = _plain(run_file, "laser", "displacement"), _plain(run_file, "laser", "t")
    assert env.samples == u.size > 50_000 and env.edges.size == 301 and env.unit == "m"
    assert env.edges[0] == t.min() and env.edges[-1] == t.max()
    assert np.nanmax(env.hi) == u.max() and np.nanmin(env.lo) == u.min()
    # bin k holds the readings with edges[k] ≤ t < edges[k+1] (the last one its end too): its extremes, computed here
    # from the plain read
    k_of = np.clip(np.searchsorted(env.edges, t, side="right") - 1, 0, 299)
    for k in (0, 17, 150, 299):
        seg = u[k_of == k]
        assert env.lo[k] == seg.min() and env.hi[k] == seg.max()


def _paused(tmp_path: Path) -> Path:
    """A DAQ-rig run in virtual time, paused 3 s into its first drive and resumed 6 s later: its laser is recorded
    at 10 kHz in the steps and at 10 Hz while paused (README, "Pause and resume")."""
    from bench.runtime.run import execute, plan_run
    from tests.conftest import ROOT

    def hook(engine, sim) -> None:  # type: ignore[no-untyped-def]
        def at(_now: float) -> None:
            if engine.snapshot.state == "running" and engine.pauses == 0 and engine.now() >= 3.0:
                engine.request_pause("the test")
            if engine.snapshot.state == "paused" and engine.now() >= 9.0:
                engine.request_resume("the test")
        sim.clock.subscribe(at)

    result = execute(plan_run(ROOT / "protocols" / "short" / "thesis-sweeps-short.toml",
                              ROOT / "rigs" / "thesis-daq-sim.toml"), tmp_path / "paused.h5", virtual=True,
                     on_engine=hook)
    assert result.state == "completed", result.reason
    return Path(result.path)


def test_a_paused_run_is_drawn_from_its_own_samples_to_the_last(tmp_path: Path) -> None:
    """`bench plot RUN laser` of a paused run drew flat blocks over the pause (0.3–2.5 mm where the file decays
    smoothly from 1.79 to 0.38 mm) and its time axis stopped short of the last sample (found by an outside tester):
    the envelope was cut into equal numbers of records, so a span of 10-kHz drive readings took in the pause's
    10-Hz readings too, drawn at the span's middle time. Every point drawn in a time bin must lie within the values
    the file has in that bin (computed here from the plain read), and the line must reach the file's last sample."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    from bench.analysis import quicklook

    run_file = _paused(tmp_path)
    u, t = _plain(run_file, "laser", "displacement"), _plain(run_file, "laser", "t")
    pause = (t > 3.5) & (t < 8.9)
    assert 40 <= pause.sum() <= 80  # the pause's 10-Hz readings, in the file
    figures: list[object] = []
    real = plt.Figure.savefig

    def keep(self: object, *args: object, **kwargs: object) -> None:
        figures.append(self)
        real(self, *args, **kwargs)  # type: ignore[arg-type]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plt.Figure, "savefig", keep)
        quicklook.quicklook(run_file, ["laser"], tmp_path / "q.png")
    (fig,) = figures
    (ax,) = [a for a in fig.axes if "laser/displacement" in a.get_ylabel()]  # type: ignore[attr-defined]
    pts = [np.c_[ln.get_xdata(), ln.get_ydata()].astype(float) for ln in ax.get_lines()
           if ln.get_transform() == ax.transData]  # the data's lines (not the step marks)
    pts += [p.vertices for c in ax.collections if isinstance(c, PolyCollection) for p in c.get_paths()]
    xy = np.concatenate(pts)
    xy = xy[np.isfinite(xy).all(axis=1)]
    assert xy[:, 0].max() == t[-1] and ax.get_xlim()[1] >= t[-1]  # drawn to the last sample
    edges = np.linspace(t[0], t[-1], 401)
    for a, b in itertools.pairwise(edges):
        drawn = xy[(xy[:, 0] >= a) & (xy[:, 0] < b), 1]
        if not drawn.size:
            continue
        has = u[(t >= a) & (t <= b)]
        assert has.size, f"drawn in {a:.3f}–{b:.3f} s, where the file has no reading"
        assert has.min() <= drawn.min() and drawn.max() <= has.max(), (
            f"{a:.3f}–{b:.3f} s: drawn {drawn.min():.3e}…{drawn.max():.3e} m, the file {has.min():.3e}…"
            f"{has.max():.3e} m")
    # and the pause is drawn: its readings are on the line
    (line,) = [ln for ln in ax.get_lines() if ln.get_label() == "_envelope"]
    x = np.asarray(line.get_xdata(), float)
    assert np.isin(t[pause], x).all()


def test_bench_plot_writes_a_png_with_units_on_every_axis(run_file: Path, tmp_path: Path) -> None:
    import matplotlib.pyplot as plt

    from bench.analysis import quicklook

    figures: list[object] = []
    real = plt.Figure.savefig

    def keep(self: object, *args: object, **kwargs: object) -> None:
        figures.append(self)
        real(self, *args, **kwargs)  # type: ignore[arg-type]

    target = tmp_path / "q.png"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plt.Figure, "savefig", keep)
        res = CliRunner().invoke(app, ["plot", str(run_file), "laser", "amplifier", "--out", str(target)])
    assert res.exit_code == 0, res.output
    assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (fig,) = figures
    labels = [ax.get_ylabel() for ax in fig.axes]  # type: ignore[attr-defined]
    assert any("laser/displacement" in s and "[m]" in s for s in labels)
    assert any("amplifier/voltage" in s and "[V]" in s for s in labels)
    assert all("[" in s for s in labels) and quicklook.FLAGS[0] not in " ".join(labels)
    # the shutdown's verified 0 V is marked on the amplifier's voltage, where the file's safe event says
    from bench.storage.runfile import open_run

    (safe,) = [text for _, _, kind, text in open_run(run_file, streams=False).event_list() if kind == "safe"]
    said = re.search(r"voltage monitor (\S+) V at (\S+) s", safe)
    assert said is not None, safe
    (amp,) = [ax for ax in fig.axes if "amplifier/voltage" in ax.get_ylabel()]  # type: ignore[attr-defined]
    (mark,) = [ln for ln in amp.get_lines() if ln.get_label() == "0 V verified at the stop"]
    assert list(mark.get_xdata()) == [float(said[2])] and list(mark.get_ydata()) == [float(said[1])]


def test_a_stream_the_file_lacks_is_one_line_naming_it(run_file: Path) -> None:
    res = CliRunner().invoke(app, ["plot", str(run_file), "motor"], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and "no stream motor" in res.output and str(run_file) in res.output


def test_out_a_folder_holds_the_figure_and_nan_pixels_warn_nothing(run_file: Path, tmp_path: Path) -> None:
    """`--out FOLDER` printed "figure: FOLDER" and wrote FOLDER.png; every plot printed numpy RuntimeWarnings for the
    pixels with no valid reading (found by an exploratory test)."""
    import warnings

    folder = tmp_path / "figures"
    folder.mkdir()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        res = CliRunner().invoke(app, ["plot", str(run_file), "--out", str(folder)], env={"COLUMNS": "300"})
    assert res.exit_code == 0, res.output
    target = folder / f"{run_file.stem}-plot.png"
    assert target.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"figure: {target}" in res.output
    assert not (tmp_path / "figures.png").exists()


def test_a_plot_that_cannot_be_written_says_which_file_in_one_line(run_file: Path, tmp_path: Path) -> None:
    """`bench plot RUN --out afile/sub/x.png`, where afile is a file, printed the OS's "[Errno 20] Not a directory:
    'afile/sub'" (an outside tester, with an unwritable folder): the line names the figure and why."""
    (tmp_path / "afile").write_text("")
    target = tmp_path / "afile" / "sub" / "x.png"
    res = CliRunner().invoke(app, ["plot", str(run_file), "--out", str(target)])
    assert res.exit_code == 2, res.output
    line = " ".join(res.output.split())
    assert f"{target}: cannot write the plot: Not a directory (errno {errno.ENOTDIR})" in line, res.output
    assert "[Errno" not in line and "Traceback" not in res.output


def test_plots_of_different_streams_are_named_by_them_and_keep_each_other(run_file: Path, tmp_path: Path) -> None:
    """`bench plot F laser` then `bench plot F amplifier` both wrote RUN-plot.png, the second replacing the first
    (found by an outside tester): the default name says the streams drawn. `--out figures` where no such folder
    is: a folder too."""
    folder = tmp_path / "figures"  # not there yet: a name without a file type is a folder (it wrote figures.png
    # and said "figure: figures", and the second plot replaced the first)
    for stream in ("laser", "amplifier"):
        res = CliRunner().invoke(app, ["plot", str(run_file), stream, "--out", str(folder)])
        target = folder / f"{run_file.stem}-plot-{stream}.png"
        assert res.exit_code == 0 and f"figure: {target}" in res.output, res.output
    assert sorted(p.name for p in folder.iterdir()) == [f"{run_file.stem}-plot-amplifier.png",
                                                        f"{run_file.stem}-plot-laser.png"]
    assert not (tmp_path / "figures.png").exists()


def test_an_explicit_out_file_that_exists_is_refused_not_replaced(run_file: Path, tmp_path: Path) -> None:
    """`bench plot F --out x.png` replaced an existing x.png silently (found by outside testers), where `bench fit
    --export` and `bench export --mat` refuse an existing file. Refused in one line naming it, the file kept; a new
    name is written whole (no temporary left beside it)."""
    target = tmp_path / "x.png"
    target.write_bytes(b"mine")
    res = CliRunner().invoke(app, ["plot", str(run_file), "laser", "--out", str(target)], env={"COLUMNS": "300"})
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1 and "Traceback" not in res.output, res.output
    assert f"--out {target}: exists; bench plot does not overwrite files" in lines[0]
    assert target.read_bytes() == b"mine"
    res = CliRunner().invoke(app, ["plot", str(run_file), "laser", "--out", str(tmp_path / "y.png")])
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.png", "y.png"]


def test_readings_out_of_time_order_are_binned_by_their_own_times(run_file: Path, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A record whose time goes back (an edited or merged file) is binned by each reading's own time: the same
    bins, extremes and vertices as the file in order (the old envelope cut it by record count)."""
    import shutil

    import bench.storage.chunks as chunks

    monkeypatch.setattr(chunks, "CHUNK_ROWS", 7_777)
    shuffled = tmp_path / "shuffled.h5"
    shutil.copy(run_file, shuffled)
    n = _plain(run_file, "laser", "t").size
    order = np.r_[np.arange(n // 2, n), np.arange(n // 2)]  # the second half first
    with h5py.File(shuffled, "r+") as f:
        for c in ("t", "displacement", "valid"):
            f[f"laser/{c}"][:n] = f[f"laser/{c}"][:n][order]
    (a,) = [e for e in envelopes(run_file, ["laser"], columns=300) if e.column == "displacement"]
    (b,) = [e for e in envelopes(shuffled, ["laser"], columns=300) if e.column == "displacement"]
    assert np.array_equal(a.edges, b.edges)
    assert np.array_equal(a.lo, b.lo, equal_nan=True) and np.array_equal(a.hi, b.hi, equal_nan=True)
    assert np.array_equal(a.t[np.isfinite(a.t)], b.t[np.isfinite(b.t)])
    assert np.array_equal(a.v[np.isfinite(a.t)], b.v[np.isfinite(b.t)])
