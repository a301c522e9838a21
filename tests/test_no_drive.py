"""A run (or simulation) whose drive is 0 V: nothing to fit, and no figure relative to the drive.

The short identification protocol with its raised cosine's amplitude set to 0 kV is run in virtual time on its own
simulated rig; the voltage monitor then shows its noise only (a few volts), well inside the band in which the
engine counts the monitor as reading 0 V. The analysis takes the band of the chain of the rig the file records: the
TREK monitor into a LabJack T7 AIN, 15.3 V (derived from the manuals' figures in tests/test_monitor_chain.py; a file
whose rig is not known is judged on the widest, tests/test_no_drive_band.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from tests.test_monitor_chain import T7_BAND

ROOT = Path(__file__).resolve().parent.parent
SHORT = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
runner = CliRunner()


@pytest.fixture(scope="module")
def zero_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A completed virtual-time run of the short protocol with a 0-kV drive."""
    from bench.runtime.run import execute, plan_run

    out = tmp_path_factory.mktemp("zero-run")
    text = SHORT.read_text(encoding="utf-8")
    assert 'amplitude = "7 kV"' in text and 'rig = "../../rigs/thesis-daq-sim.toml"' in text
    text = text.replace('amplitude = "7 kV"', 'amplitude = "0 kV"').replace(
        'rig = "../../rigs/thesis-daq-sim.toml"', f'rig = "{ROOT / "rigs" / "thesis-daq-sim.toml"}"')
    protocol = out / "zero.toml"
    protocol.write_text(text, encoding="utf-8")
    result = execute(plan_run(protocol), out / "zero.h5", virtual=True)
    assert result.state == "completed", result.reason
    return Path(result.path)


def test_fit_of_an_undriven_run_is_refused_in_one_line(zero_run: Path) -> None:
    res = runner.invoke(app, ["fit", str(zero_run), "--population", "6", "--generations", "2"],
                        env={"COLUMNS": "300"})
    assert res.exit_code == 2, res.output
    assert "zero-size array" not in res.output
    err = [line for line in res.output.splitlines() if line.startswith("error:")]
    assert len(err) == 1, res.output
    assert str(zero_run) in err[0] and f"never driven above {T7_BAND:.3g} V" in err[0] and "identifiable" in err[0]
    assert not Path(str(zero_run).removesuffix(".h5") + ".fit.hdf5").exists()  # nothing was fitted or stored


def test_report_of_an_undriven_run_gives_no_lag_or_creep(zero_run: Path, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    res = runner.invoke(app, ["report", str(zero_run), "--out", str(tmp_path / "text")], env={"COLUMNS": "300"})
    assert res.exit_code == 0, res.output
    assert "not driven, so lag and creep" in res.output
    lag_row = next(line for line in res.output.splitlines() if "lag 1 [s]" in line)
    assert "–" in lag_row and not any(c.isdigit() for c in lag_row.split("lag 1 [s]")[1]), lag_row
    # the undriven run's figures were drawn above; the JSON's figures of merit do not need them drawn again (the
    # PNG at 300 dpi, PDF and SVG of the 10-kHz record: most of this test's time)
    import matplotlib.pyplot as plt
    from matplotlib.figure import Figure

    import bench.report

    def not_drawn(fig: Figure, path: Path, close: bool = True) -> Path:
        plt.close(fig)
        return path

    monkeypatch.setattr(bench.report, "save_figure", not_drawn)
    res = runner.invoke(app, ["report", str(zero_run), "--out", str(tmp_path / "json"), "--json"])
    assert res.exit_code == 0, res.output
    (step,) = json.loads(res.output)["runs"][0]["steps"]
    assert step["voltage_V"] < T7_BAND  # the monitor's noise, not a drive
    assert step["figures"]["lag_first"] is None and step["figures"]["creep"] is None
    assert step["figures"]["peak_first"] is not None  # what the laser saw is still reported


def test_simulate_thesis_at_0_V_gives_no_lag_or_creep() -> None:
    res = runner.invoke(app, ["simulate", "thesis", "--voltage", "0", "--frequency", "0.1"], env={"COLUMNS": "300"})
    assert res.exit_code == 0, res.output
    rows = [line for line in res.output.splitlines() if line.startswith("│")]
    assert len(rows) == 2, res.output  # 20 s at 0.1 Hz: two cycles
    for row in rows:
        assert row.split("│")[4].strip() == "–", row  # the lag column
    assert "not driven, so lag and creep" in res.output
    assert "creep –" in res.output

