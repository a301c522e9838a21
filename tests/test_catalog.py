"""The run catalogue on SQLite and on a real PostgreSQL server (started here in a temporary cluster), and the
specimen history built from it.

Expected values are computed here from the run files with h5py (and, for the fitted run, from the protocol's
waveform), never taken from the catalogue's own account.
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests import catalog_helpers
from tests.campaign_kill import kill_at_step
from tests.catalog_helpers import (
    COLUMNS,
    IDENT,
    SPECIMEN,
    SWEEPS,
    THRESHOLD_V,
    Catalog,
    _bench,
    _bench_here,
    _env,
    _expected,
    row_from_attrs,
)
from tests.conftest import ROOT

pg_server = catalog_helpers.pg_server  # the shared fixtures (pytest finds them by name in the module)
catalog_url = catalog_helpers.catalog_url

# ---- a lab folder: a killed campaign, its resumption, a fitted run, all on one specimen ----------------------------


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    runs = tmp_path_factory.mktemp("lab") / "runs"
    env = _env(tmp_path_factory.mktemp("state"))
    # the short sweeps with 30-s drives (10 cycles each): long enough in virtual time for the recorder to flush
    # the first drive (every 0.2 s of wall time) before the kill; a wall-clock run would trip on a loaded host
    sweeps = runs.parent / "sweeps-30s.toml"
    sweeps.write_text(SWEEPS.read_text().replace("duration_s = 5.0", "duration_s = 30.0")
                      .replace('rig = "../../rigs/', f'rig = "{ROOT}/rigs/'))
    proc = subprocess.Popen([sys.executable, "-m", "bench", "run", str(sweeps), "--virtual-time", "--out", str(runs),
                             "--no-live", "--specimen-id", SPECIMEN, "--operator", "ada"], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    kill_at_step(proc, runs, 4, 180)  # once the 7-kV drive has started: no end recorded, no end row in the catalogue
    killed = next(runs.glob("*.h5"))
    # the further commands in this process (the campaign above was a `python -m bench run`): its hooks write the
    # same catalogue rows, without a Python start-up and its imports each (15 s of this fixture's 25)
    resumed = _bench_here("run", "--resume", str(killed), "--virtual-time", "--no-live", "--why",  # killed: latched
                          "output checked at 0 V after the kill", env=env)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    second = next(p for p in runs.glob("*.h5") if p != killed)
    ident = _bench_here("run", str(IDENT), "--virtual-time", "--out", str(runs), "--no-live", "--specimen-id",
                        SPECIMEN, env=env)
    assert ident.returncode == 0, ident.stdout + ident.stderr
    fitted = next(p for p in runs.glob("*.h5") if p not in (killed, second))
    for target in (second, fitted):  # the campaign (stored with both of its files), then the third run alone
        fit = _bench_here("fit", str(target), "--population", "6", "--generations", "1", "--no-polish", "--starts",
                          "1", "--no-intervals", "--json", env=env)
        assert fit.returncode == 0, fit.stderr
    return {"runs": runs, "killed": killed, "resumed": second, "fitted": fitted, "state": runs.parent}


def _comparable(rows: list[dict]) -> list[tuple]:
    return sorted(tuple(r[c] for c in COLUMNS) for r in rows)


def _list(lab: dict[str, Path], url: str, *extra: str, here: bool = False) -> list[dict]:
    out = (_bench_here if here else _bench)("runs", "list", "--dir", str(lab["runs"]), "--catalog", url, "--json",
                                            *extra, env=_env(lab["state"]))
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_the_runs_wrote_their_rows_and_a_lost_end_is_reconciled(lab: dict[str, Path]) -> None:
    """The hooks wrote the default SQLite catalogue beside the runs: the killed run only its start row; listing
    reconciles it (and the fit written after the run) from the files."""
    url = f"sqlite:///{lab['runs'] / 'catalog.sqlite'}"
    with Catalog(url) as cat:
        before = {Path(r["path"]).name: r for r in cat.rows()}
    assert set(before) == {lab["killed"].name, lab["resumed"].name, lab["fitted"].name}
    assert before[lab["killed"].name]["state"] == "running" and before[lab["killed"].name]["signature"] == ""
    assert before[lab["resumed"].name]["state"] == "completed"
    assert json.loads(before[lab["fitted"].name]["fits"]) == []  # the fit came after the run's end
    listed = {Path(r["path"]).name: r for r in _list(lab, url)}
    assert listed[lab["killed"].name]["complete"] is False
    assert "killed" in listed[lab["killed"].name]["incomplete_reason"]
    from bench.storage.runfile import open_run

    done = open_run(lab["killed"], streams=False).completed_steps()  # what the kill let the file confirm
    assert listed[lab["killed"].name]["steps_completed"] == len(done) < 6
    assert listed[lab["killed"].name]["steps_total"] == 6  # chamber, drive, recovery × 2 sweep points
    assert listed[lab["resumed"].name]["previous_file"] == str(lab["killed"].resolve())
    # a finished resume ran all of its own steps, those from where the campaign resumed: it read "4/6" and, in
    # inspect, "recorded up to 40.5 s of 60.0 s planned", as if it had not finished (an outside tester)
    resumed = open_run(lab["resumed"], streams=False)
    first = int(resumed.attrs["resumed_at_step"])
    row = listed[lab["resumed"].name]
    assert 0 < first and row["steps_total"] == 6 - first == row["steps_completed"], row
    shown = _bench_here("inspect", str(lab["resumed"]), env={**_env(lab["state"]), "COLUMNS": "300"})
    left = float(resumed.attrs["duration_planned"]) - float(resumed.program["t_start"][first])
    assert f"of {left:.1f} s planned (resumed at step {first + 1} of 6" in " ".join(shown.stdout.split()), \
        shown.stdout
    assert len(listed[lab["fitted"].name]["fits"]) == 1
    assert len(listed[lab["killed"].name]["fits"]) == len(listed[lab["resumed"].name]["fits"]) == 1  # the campaign's
    # the filters: the same command in this process (the listing above went through `python -m bench`)
    assert [r["protocol_name"] for r in _list(lab, url, "--protocol", "thesis-identification-short", here=True)] == \
        ["thesis-identification-short"]
    assert {Path(r["path"]).name for r in _list(lab, url, "--state", "completed", here=True)} == \
        {lab["resumed"].name, lab["fitted"].name}
    assert len(_list(lab, url, "--specimen", SPECIMEN, here=True)) == 3
    assert _list(lab, url, "--specimen", "S8", here=True) == []
    assert _list(lab, url, "--since", "2999-01-01", here=True) == []
    assert len(_list(lab, url, "--since", "2000-01-01", here=True)) == 3
    bad = _bench_here("runs", "list", "--dir", str(lab["runs"]), "--since", "monday", env=_env(lab["state"]))
    assert bad.returncode == 2 and "--since" in bad.stderr and "Traceback" not in bad.stderr


def test_a_deleted_or_stale_catalogue_is_rebuilt_to_the_same_rows(lab: dict[str, Path], catalog_url: str) -> None:
    env = _env(lab["state"])
    files = sorted(lab["runs"].glob("*.h5"))
    out = _bench("catalog", "rebuild", str(lab["runs"]), "--catalog", catalog_url, "--json", env=env)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["rows"] == len(files) == 3
    with Catalog(catalog_url) as cat:
        rebuilt = cat.rows()
        # stale: every end lost (start rows only), one row gone, one row of a file that no longer exists
        cat.delete(rebuilt[0]["host"], [r["path"] for r in rebuilt])
        from bench.storage.runfile import open_run

        cat.upsert([row_from_attrs(p, open_run(p, streams=False).attrs) for p in files[1:]])
        cat.upsert([{**row_from_attrs(lab["runs"] / "gone.h5", {"specimen_id": SPECIMEN}), "state": "completed"}])
    listed = _list(lab, catalog_url, here=True)
    with Catalog(catalog_url) as cat:
        reconciled = cat.rows()
    assert _comparable(reconciled) == _comparable(rebuilt)
    assert [r["path"] for r in listed] == [r["path"] for r in rebuilt]
    # deleted: the whole catalogue gone, rebuilt to the same rows
    with Catalog(catalog_url) as cat:
        cat.runs.drop(cat.engine)
    assert _bench_here("catalog", "rebuild", str(lab["runs"]), "--catalog", catalog_url, env=env).returncode == 0
    with Catalog(catalog_url) as cat:
        assert _comparable(cat.rows()) == _comparable(rebuilt)
    # and the backends agree: the same rows as the hooks' SQLite catalogue once reconciled
    with Catalog(f"sqlite:///{lab['runs'] / 'catalog.sqlite'}") as cat:
        from bench.storage.catalog import reconcile

        reconcile(cat, lab["runs"])
        assert _comparable(cat.rows()) == _comparable(rebuilt)


WRITER = """
import sys, time
from pathlib import Path
from bench.storage.catalog import record_end, record_start
from bench.storage.runfile import open_run
url, go, paths = sys.argv[1], Path(sys.argv[2]), [Path(p) for p in sys.argv[3:]]
attrs = open_run(paths[0], streams=False).attrs
while not go.exists():
    time.sleep(0.01)
for p in paths:
    record_start(p, attrs, url)
    record_end(p, url)
"""


def test_two_processes_writing_runs_at_once_lose_nothing(lab: dict[str, Path], catalog_url: str,
                                                         tmp_path: Path) -> None:
    """Two benches' hooks (start row, then end row read from the file) on one catalogue at the same time."""
    folder = tmp_path / "copies"
    folder.mkdir()
    copies = []
    for k in range(24):
        copies.append(folder / f"run-{k:02d}.h5")
        shutil.copy(lab["fitted"], copies[-1])
    go = tmp_path / "go"
    env = _env(lab["state"])
    procs = [subprocess.Popen([sys.executable, "-c", WRITER, catalog_url, str(go), *map(str, copies[k::2])],
                              cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k in range(2)]
    go.touch()
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err
        assert "catalogue not written" not in err, err  # a write given up is a warning line: none here
    with Catalog(catalog_url) as cat:
        rows = cat.rows()
        assert sorted(Path(r["path"]).name for r in rows) == sorted(p.name for p in copies)
        assert {r["state"] for r in rows} == {"completed"} and all(r["signature"] for r in rows)
        from bench.storage.catalog import reconcile

        done = reconcile(cat, folder)
    assert (done.added, done.updated, done.removed) == (0, 0, 0)  # nothing left to reconcile: nothing was lost



def test_specimen_history_of_three_runs(lab: dict[str, Path], catalog_url: str,
                                       monkeypatch: pytest.MonkeyPatch) -> None:
    env = _env(lab["state"])
    plot = lab["state"] / f"history-{catalog_url.split(':')[0]}.png"
    # the SQLite catalogue's through `python -m bench`, the PostgreSQL one's in this process (a start-up saved)
    bench = _bench if catalog_url.startswith("sqlite") else _bench_here
    out = bench("specimen", "show", SPECIMEN, "--dir", str(lab["runs"]), "--catalog", catalog_url, "--plot", str(plot),
                "--json", env=env)
    assert out.returncode == 0, out.stderr
    h = json.loads(out.stdout)
    order = [lab["killed"], lab["resumed"], lab["fitted"]]
    assert [r["file"] for r in h["runs"]] == [str(p.resolve()) for p in order]
    per = [_expected(p) for p in order]
    assert [r["hv_cycles"] for r in h["runs"]] == [e[1] for e in per]
    for r, e in zip(h["runs"], per, strict=True):
        assert r["hv_time_s"] == pytest.approx(e[0], rel=1e-9, abs=1e-9)
    assert h["hv_time_s"] == pytest.approx(sum(e[0] for e in per), rel=1e-9)
    assert h["hv_cycles"] == sum(e[1] for e in per)
    assert [r["cumulative_cycles"] for r in h["runs"]] == list(np.cumsum([e[1] for e in per]))
    # the fitted run against its protocol: V = 7 kV (1 − cos 2πft)/2, f = 1/9 Hz, 10 s: |V| > 500 V while
    # cos 2πft < 1 − 2·500/7000, i.e. for 0.8278 of each full period (9 s) plus 10 s − 9 s − 0.541/(2πf) of the next
    phi = math.acos(1 - 2 * THRESHOLD_V / 7000)
    model_hv = 9 * (1 - phi / math.pi) + (1 - phi / (2 * math.pi / 9))
    assert h["runs"][2]["hv_time_s"] == pytest.approx(model_hv, abs=0.25)  # the amplifier's slew and lag
    assert h["runs"][2]["hv_cycles"] == 2  # one full cycle, the second begun (819 V at 10 s on the model)
    # the killed file holds the 5-kV drive (killed later, in the 7-kV one); the resumed file the 7-kV drive
    assert per[0][1] >= 1 and per[1][1] >= 1
    # peak nominal field = max |V| / L3 of the stored model; ratio to the rig's breakdown field
    rig = tomllib.loads((ROOT / "rigs" / "thesis-daq-sim.toml").read_text())
    breakdown = rig["specimen"]["breakdown_field_V_per_m"]
    spec = json.loads(h5py.File(lab["fitted"], "r", libver="latest", swmr=True).attrs["specimen"])
    peak = max(e[2] for e in per) / spec["model"]["L3"]
    assert h["max_nominal_field_V_per_m"] == pytest.approx(peak, rel=1e-9)
    # the breakdown field is a true-field limit: the ratio is the true field E = |V|λ²/L3 (physics.md §1.2), λ =
    # λ_pre + u/L_d (§1.4) from each file's laser at its voltage samples, over it — never the nominal field's
    model = spec["model"]
    true = []
    for p in order:
        with h5py.File(p, "r", libver="latest", swmr=True) as f:
            n = dict(zip(json.loads(f["status/samples"].attrs["names"]), f["status/samples"][:], strict=True))
            tv, v = f["amplifier/t"][:n["amplifier"]], np.abs(f["amplifier/voltage"][:n["amplifier"]])
            tu, u = f["laser/t"][:n["laser"]], f["laser/displacement"][:n["laser"]]
        ok = np.isfinite(u)
        lam = model["lambda_pre"] + np.interp(tv, tu[ok], u[ok]) / model["L_d"]
        true.append(float(np.nanmax(v * lam**2 / model["L3"])))
    assert h["max_true_field_V_per_m"] == pytest.approx(max(true), rel=1e-9)
    assert h["field_ratio"] == pytest.approx(max(true) / breakdown, rel=1e-9)
    assert 0.28 < h["field_ratio"] < 0.5  # 7 kV across 1 mm stretched to λ ≈ 2.2–2.3 against 100 MV/m
    # failures: the killed file, and only it
    assert [f["file"] for f in h["failures"]] == [str(lab["killed"].resolve())]
    # the fits: the campaign's (stored with both of its files) once, at the cycles after the resumed file; the
    # third run's at the cycles of the whole life; each with its fit file's values
    stored = []
    for run in (lab["resumed"], lab["fitted"]):
        with h5py.File(run.with_suffix(".fit.hdf5"), "r") as f:
            (g,) = f["fit"].values()
            stored.append(dict(zip(g["names"].asstr()[:], g["values"][:], strict=True)))
    assert set(h["parameters"]) == set(stored[0]) == set(stored[1])
    for name, pts in h["parameters"].items():
        assert [p["cumulative_cycles"] for p in pts] == [per[0][1] + per[1][1], sum(e[1] for e in per)]
        assert [p["value"] for p in pts] == [pytest.approx(stored[0][name], rel=1e-12),
                                             pytest.approx(stored[1][name], rel=1e-12)]
    assert h["plot"] == str(plot) and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the table in text: the plot, checked above, not drawn again (its 16 panels are seconds of matplotlib)
    from bench.storage import catalog

    monkeypatch.setattr(catalog, "plot_history", lambda _h, _specimen, out: out)
    text = _bench_here("specimen", "show", SPECIMEN, "--dir", str(lab["runs"]), "--catalog", catalog_url, "--plot",
                       str(plot), env=env)
    assert text.returncode == 0 and f"> {THRESHOLD_V:g} V" in text.stdout and "killed" in text.stdout
    with contextlib.suppress(FileNotFoundError):
        plot.unlink()
    missing = _bench_here("specimen", "show", "S99", "--dir", str(lab["runs"]), "--catalog", catalog_url, env=env)
    assert missing.returncode == 2 and "S99" in missing.stderr and "Traceback" not in missing.stderr


def test_statistics_read_in_chunks_equal_the_plain_count(lab: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """A long run is read in chunks: a chunk boundary (here every 997 samples, inside rises and plateaus) changes
    nothing against the plain loop over the whole record."""
    from bench.storage import catalog, hv_stats

    monkeypatch.setattr(hv_stats, "CHUNK", 997)
    for path in (lab["killed"], lab["resumed"], lab["fitted"]):
        hv, rises, peak = _expected(path)
        got = catalog.hv_statistics(path)
        assert (got.cycles, got.max_voltage_V) == (rises, pytest.approx(peak, rel=1e-12))
        assert got.hv_time_s == pytest.approx(hv, rel=1e-9, abs=1e-9)
