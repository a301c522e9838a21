"""bench plot: a quick-look figure of any streams; the envelope keeps every extreme of the record (checked against
the file as plain h5py reads it), units on every axis, one line of error for a stream the file lacks."""

from __future__ import annotations

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

    monkeypatch.setattr(chunks, "CHUNK_ROWS", 7_777)  # spans cross chunk edges
    (env,) = [e for e in envelopes(run_file, ["laser"], columns=300) if e.column == "displacement"]
    u = _plain(run_file, "laser", "displacement")
    assert env.samples == u.size > 50_000 and env.t.size == 300 and env.unit == "m"
    assert env.hi.max() == u.max() and env.lo.min() == u.min()
    # span k covers records ⌊k·n/300⌋ … ⌊(k+1)·n/300⌋−1: its extremes, computed here from the plain read
    edges = np.linspace(0, u.size, 301).astype(int)
    for k in (0, 17, 150, 299):
        seg = u[edges[k]:edges[k + 1]]
        assert env.lo[k] == seg.min() and env.hi[k] == seg.max()


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
