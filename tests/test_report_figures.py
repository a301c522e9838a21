"""Report figures that show what matters (issue 26, item 6), checked on the saved figure's layout.

Each figure is built by bench.report, saved as the report saves it (PNG, PDF, SVG), and then read back through
matplotlib's renderer: the extents are those of the saved layout, not pixels. The expectations come from the
run file and the stored fit (the residual's rms is the one `bench fit` stored), never from the figure code.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.text import Annotation
from matplotlib.transforms import Bbox

from bench.analysis.runs import analyse
from bench.identify.core import FitSettings, fit
from bench.identify.problems import MembraneProblem
from bench.identify.store import read_fits, write_fit
from bench.report import (
    isopotential_loop_figures,
    save_figure,
    table3_figure,
    thesis_loop_figure,
    thesis_time_figure,
)
from bench.storage.runfile import open_run


@pytest.fixture(scope="module")
def fitted_run(tmp_path_factory: pytest.TempPathFactory, short_run: Path) -> Path:
    """The short thesis record (10 s raised cosine, 1 s rest) with a quick membrane fit in its fit file."""
    import shutil

    d = tmp_path_factory.mktemp("fitted")
    # the session's run of that protocol on its rig (conftest's short_run, made once), copied: the fit file goes
    # beside this copy
    path = d / "run.h5"
    shutil.copy2(short_run, path)
    coarse, fine = MembraneProblem([path], h=5e-4), MembraneProblem([path], h=1e-4)  # as `bench fit` does
    result = fit(coarse, FitSettings(population=6, generations=2, polish=False), fine=fine)
    write_fit(path, "membrane", result, [r.source for r in coarse.records], sidecar=True)
    return path


def _saved(fig: Figure, path: Path) -> Figure:
    save_figure(fig, path, close=False)
    assert path.read_bytes()[:4] == b"\x89PNG" and path.with_suffix(".svg").exists()
    return fig


def _data_axes(fig: Figure) -> list[Axes]:
    """Axes holding data (colour bars excluded)."""
    return [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]


def _assert_legend_outside(fig: Figure) -> None:
    """The figure's legends lie inside the figure and overlap no axes' area (where the data are drawn)."""
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    legends = [*fig.legends, *(leg for ax in fig.axes if (leg := ax.get_legend()) is not None)]
    assert legends, "no legend"
    fig_box = fig.bbox
    for leg in legends:
        box = leg.get_window_extent(renderer)
        assert fig_box.x0 - 1 <= box.x0 and box.x1 <= fig_box.x1 + 1 and fig_box.y0 - 1 <= box.y0 \
            and box.y1 <= fig_box.y1 + 1, "legend cut off"
        for ax in _data_axes(fig):
            area = ax.get_window_extent(renderer)
            inter = Bbox.intersection(box, area)
            assert inter is None or inter.width <= 0 or inter.height <= 0, f"legend over the data of {_title(ax)}"


def _title(ax: Axes) -> str:
    return " ".join(ax.get_title(loc) for loc in ("left", "center", "right")).strip()


def _line(ax: Axes, starts: str) -> Line2D:
    found = [ln for ln in ax.get_lines() if str(ln.get_label()).startswith(starts)]
    assert len(found) == 1, [ln.get_label() for ln in ax.get_lines()]
    return found[0]


def test_fit_figure_has_a_residual_panel_with_the_fits_rms_and_the_legend_off_the_data(fitted_run: Path,
                                                                                       tmp_path: Path) -> None:
    fig = _saved(thesis_time_figure(analyse(fitted_run)), tmp_path / "t.png")
    stored_rms = read_fits(fitted_run)[-1]["rms"]  # what `bench fit` computed on the same records
    main = next(ax for ax in fig.axes if ax.get_title().endswith("displacement vs time"))
    residual = [ax for ax in fig.axes if "residual" in _title(ax)]
    assert len(residual) == 1, [_title(ax) for ax in fig.axes]
    panel = residual[0]
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    # under the main axes, on the same time axis
    assert panel.get_window_extent(renderer).y1 <= main.get_window_extent(renderer).y0
    assert panel.get_shared_x_axes().joined(panel, main)
    assert f"rms {stored_rms * 1e6:.1f} µm" in _title(panel)
    assert "model − record" in _title(panel)
    # the residual drawn is model minus record: its rms is the stored one
    y = np.asarray(panel.get_lines()[0].get_ydata(), float)
    assert float(np.sqrt(np.nanmean(y**2))) == pytest.approx(stored_rms * 1e6, rel=1e-3)
    _assert_legend_outside(fig)


def test_model_curve_stays_within_the_laser_record(fitted_run: Path, tmp_path: Path) -> None:
    fig = _saved(thesis_time_figure(analyse(fitted_run)), tmp_path / "t.png")
    laser = open_run(fitted_run).streams["laser"]
    ok = laser.columns["valid"] > 0
    first, last = float(laser.t[ok][0]), float(laser.t[ok][-1])
    assert float(open_run(fitted_run).updated) > last + 0.1  # the file runs on past the laser (the old bug's case)
    model = _line(fig.axes[0], "fitted model")
    t = np.asarray(model.get_xdata(), float)
    assert t.min() >= first - 1e-9 and t.max() <= last + 1e-9
    assert t.max() > last - 0.05  # ... and reaches its end


def test_commanded_and_measured_voltage_are_both_visible_and_the_axis_wears_their_colour(fitted_run: Path,
                                                                                        tmp_path: Path) -> None:
    fig = _saved(thesis_time_figure(analyse(fitted_run)), tmp_path / "t.png")
    right = next(ax for ax in fig.axes if ax.get_ylabel().startswith("voltage"))
    commanded, measured = _line(right, "commanded voltage"), _line(right, "measured voltage")
    for ln in (commanded, measured):
        assert ln.get_visible() and np.asarray(ln.get_xdata()).size > 100
    assert commanded.get_linestyle() != measured.get_linestyle()
    assert commanded.get_color() != measured.get_color()
    assert commanded.get_zorder() > measured.get_zorder()  # the command is drawn on top, not hidden
    label_colour = right.yaxis.label.get_color()
    assert label_colour == measured.get_color()
    assert all(t.get_color() == label_colour for t in right.get_yticklabels())


def _assert_arrows_follow(ax: Axes) -> None:
    """Each loop carries arrows whose head lies further along the loop's samples than their tail."""
    arrows = [c for c in ax.get_children() if isinstance(c, Annotation) and c.arrow_patch is not None]
    lines = ax.get_lines()
    assert lines and len(arrows) >= 2 * len(lines)
    for a in arrows:
        head, tail = np.array(a.xy, float), np.array(a.xyann, float)
        xy = None
        for ln in lines:
            pts = np.column_stack([ln.get_xdata(), ln.get_ydata()]).astype(float)
            if np.isclose(pts, head).all(axis=1).any() and np.isclose(pts, tail).all(axis=1).any():
                xy = pts
        assert xy is not None, "arrow not on a loop"
        i_head = np.flatnonzero(np.isclose(xy, head).all(axis=1))[0]
        i_tail = np.flatnonzero(np.isclose(xy, tail).all(axis=1))[0]
        assert i_head > i_tail


def test_thesis_loop_has_direction_arrows_and_its_legend_outside(fitted_run: Path, tmp_path: Path) -> None:
    fig = _saved(thesis_loop_figure(analyse(fitted_run)), tmp_path / "loop.png")
    _assert_arrows_follow(fig.axes[0])
    _assert_legend_outside(fig)


def test_isopotential_loops_have_arrows_and_legends_outside(isopotential_run: Path, tmp_path: Path) -> None:
    # the short isopotential campaign on its rig, run once for the session (conftest; test_analysis reads it too)
    figs = isopotential_loop_figures(analyse(isopotential_run))
    assert list(figs) == ["isopotential_p1_dx90.png"]  # prototype #1, the protocol's 90 mm stroke
    fig = _saved(figs["isopotential_p1_dx90.png"], tmp_path / "iso.png")
    _assert_arrows_follow(fig.axes[0])
    _assert_legend_outside(fig)


def test_table3_figure_shows_each_cell_of_the_campaign_grid(tmp_path: Path) -> None:
    # a grid as `bench report` builds it (bench.cli.analysis.table3): #2 has no 7-kV step
    grid = {"voltages_kV": [0, 7], "rows": [
        {"prototype": 1, "stroke_m": 0.09, "frequencies_Hz": [0.1], "loss": {"0": 0.2314, "7": 0.3478}},
        {"prototype": 2, "stroke_m": 0.07, "frequencies_Hz": [0.1], "loss": {"0": 0.1950}}]}
    fig = _saved(table3_figure(grid), tmp_path / "table3.png")
    ax = _data_axes(fig)[0]
    cells = {(round(t.get_position()[0]), round(t.get_position()[1])): t.get_text() for t in ax.texts}
    assert cells == {(0, 0): "23.1", (1, 0): "34.8", (0, 1): "19.5", (1, 1): "–"}
    assert [t.get_text() for t in ax.get_xticklabels()] == ["0 kV", "7 kV"]
    assert [t.get_text() for t in ax.get_yticklabels()] == ["#1, Δx 90 mm", "#2, Δx 70 mm"]


def test_a_fit_stored_before_the_monitor_calibration_still_draws(short_run: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """A membrane fit stored before V_gain/V_offset were fitted (14 values) on a DAQ record, whose problem now has
    16 parameters: matched by name, the calibration at its nominal (no error); a fit lacking a model parameter is
    one error naming the file."""
    import bench.report as report_module
    from bench.identify.problems import MembraneProblem

    prob = MembraneProblem([short_run], h=1e-4)
    assert prob.names[prob.n_model:] == ["V_gain", "V_offset"]  # the DAQ record's measured voltage
    names = list(prob.names[:prob.n_model])
    values = list(prob.reference().values())
    monkeypatch.setattr(report_module, "read_fits",
                        lambda _p: [{"model": "membrane", "names": names, "values": values, "rms": 0.0}])
    drawn = report_module.fitted_membrane(short_run)
    assert drawn is not None and drawn["model"].size == drawn["record"].size > 0
    assert np.isfinite(drawn["model"]).all()
    monkeypatch.setattr(report_module, "read_fits",
                        lambda _p: [{"model": "membrane", "names": names[1:], "values": values[1:], "rms": 0.0}])
    with pytest.raises(ValueError, match=f"run file {short_run}: its stored membrane fit lacks {names[0]}"):
        report_module.fitted_membrane(short_run)
