"""bench export: CSV per stream with units in the header, MATLAB file via scipy.io; values as in the HDF5 file."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from scipy.io import loadmat
from typer.testing import CliRunner

from bench.cli import app

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture
def run_file(short_run: Path) -> Path:
    return short_run


def test_csv_export_has_units_in_headers_and_the_file_values(run_file: Path, tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["export", str(run_file), "--csv", str(tmp_path / "csv")])
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (tmp_path / "csv").iterdir())
    assert names == ["amplifier.csv", "events.csv", "laser.csv", "metadata.json", "safe_state.csv", "setpoints.csv"]
    with (tmp_path / "csv" / "laser.csv").open(encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    assert rows[0][:2] == ["t [s]", "displacement [m]"] and "valid [1]" in rows[0]
    with h5py.File(run_file, "r") as f:
        n = int(dict(zip(json.loads(f["status/samples"].attrs["names"]), f["status/samples"][:],
                         strict=True))["laser"])
        t, u = f["laser/t"][:n], f["laser/displacement"][:n]
        volts = f["amplifier/commanded"][: len(f["amplifier/t"])]  # hardware-timed default rig
    assert len(rows) - 1 == n > 50_000  # 10 kHz over the active step
    got = np.array([[float(r[0]), float(r[1])] for r in rows[1:]])
    # the instruments' precision, not every bit: time to 12 significant digits, values to 9 (half a unit in the
    # last written digit, relative)
    np.testing.assert_allclose(got[:, 0], t, rtol=5e-12, atol=0)
    np.testing.assert_allclose(got[:, 1], u, rtol=5e-9, atol=0)
    assert max(len(r[1].lstrip("-").replace(".", "").lstrip("0").split("e")[0]) for r in rows[1:]) <= 9
    with (tmp_path / "csv" / "amplifier.csv").open(encoding="utf-8") as fh:
        amp = list(csv.DictReader(fh))
    assert max(float(r["commanded [V]"]) for r in amp) == pytest.approx(volts.max()) and volts.max() > 5000
    with (tmp_path / "csv" / "events.csv").open(encoding="utf-8") as fh:
        events = list(csv.DictReader(fh))
    assert events[0]["kind"] == "run" and any(e["kind"] == "end" for e in events)
    meta = json.loads((tmp_path / "csv" / "metadata.json").read_text(encoding="utf-8"))
    assert meta["protocol_name"] == "thesis-identification-short" and meta["complete"] is True


def test_mat_export_reads_back_in_scipy_with_units(run_file: Path, tmp_path: Path) -> None:
    target = tmp_path / "out" / "run.mat"
    res = CliRunner().invoke(app, ["export", str(run_file), "--mat", str(target)])
    assert res.exit_code == 0, res.output
    m = loadmat(target, simplify_cells=True)
    assert {"setpoints", "amplifier", "laser", "events", "metadata"} <= set(m)
    assert m["laser"]["units"] == {"t": "s", "displacement": "m", "valid": "1"}  # on the DAQ's scan clock
    assert m["amplifier"]["units"]["voltage"] == "V" and m["amplifier"]["units"]["current"] == "A"
    with h5py.File(run_file, "r") as f:
        n = len(m["laser"]["t"])
        np.testing.assert_array_equal(m["laser"]["displacement"], f["laser/displacement"][:n])
    assert n > 50_000
    assert "end" in list(m["events"]["kind"])
    assert m["metadata"]["rig_name"] == "thesis-daq-sim"


def test_export_needs_a_target_and_a_run_file(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["export", str(tmp_path / "missing.h5"), "--csv", str(tmp_path)])
    assert res.exit_code == 2 and "not found" in res.output
    res = CliRunner().invoke(app, ["export", str(tmp_path / "missing.h5")])
    assert res.exit_code == 2 and "--csv" in res.output


def test_mat73_reads_back_in_an_independent_reader_with_the_file_values(run_file: Path, tmp_path: Path) -> None:
    import mat73

    target = tmp_path / "run73.mat"
    res = CliRunner().invoke(app, ["export", str(run_file), "--mat", str(target), "--mat-version", "7.3"])
    assert res.exit_code == 0, res.output
    assert target.read_bytes()[:19] == b"MATLAB 7.3 MAT-file" and target.read_bytes()[126:128] == b"IM"
    m = mat73.loadmat(str(target))
    with h5py.File(run_file, "r") as f:
        n = len(m["laser"]["t"])
        np.testing.assert_array_equal(m["laser"]["displacement"], f["laser/displacement"][:n])
        np.testing.assert_array_equal(m["amplifier"]["t"], f["amplifier/t"][: len(m["amplifier"]["t"])])
    assert n > 50_000
    assert m["laser"]["units"]["displacement"] == "m" and m["amplifier"]["units"]["current"] == "A"
    assert m["metadata"]["rig_name"] == "thesis-daq-sim"
    kinds = [k[0] if isinstance(k, list) else k for k in m["events"]["kind"]]  # an n×1 cell: rows of one
    assert kinds[0] == "run" and "end" in kinds and len(kinds) == len(m["events"]["t"])


def test_auto_picks_v73_for_a_stream_beyond_the_v5_budget(run_file: Path, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    import bench.storage.export as export

    assert export.mat_version(run_file) == "5"  # a short run: every stream far below the budget
    monkeypatch.setattr(export, "MAT5_MAX_STREAM_BYTES", 1000)
    assert export.mat_version(run_file) == "7.3"


def test_streams_are_read_in_chunks_of_the_stated_size(run_file: Path, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import bench.storage.chunks as chunked
    import bench.storage.export as export

    reads: list[int] = []
    chunks = chunked.StreamChunks.chunks

    def counted(self: chunked.StreamChunks, stream: str, rows: int | None = None):  # type: ignore[no-untyped-def]
        for c in chunks(self, stream, rows):
            reads.append(c["t"].size)
            yield c

    monkeypatch.setattr(chunked, "CHUNK_ROWS", 10_000)
    monkeypatch.setattr(chunked.StreamChunks, "chunks", counted)
    files = export.to_csv(run_file, tmp_path / "csv")
    with h5py.File(run_file, "r") as f:
        n = int(dict(zip(json.loads(f["status/samples"].attrs["names"]), f["status/samples"][:],
                         strict=True))["laser"])
    laser = (tmp_path / "csv" / "laser.csv").read_text(encoding="utf-8").count("\n") - 1
    assert laser == n and max(reads) == 10_000 and len(files) == 6  # no read larger than a chunk


@pytest.mark.parametrize("kind", ["csv", "mat73"])
def test_progress_is_told_the_share_of_records_written_up_to_all(run_file: Path, tmp_path: Path, kind: str,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    import bench.storage.chunks as chunked
    import bench.storage.export as export

    monkeypatch.setattr(chunked, "CHUNK_ROWS", 20_000)
    seen: list[float] = []
    if kind == "csv":
        export.to_csv(run_file, tmp_path / "csv", progress=seen.append)
    else:
        export.to_mat(run_file, tmp_path / "run.mat", "7.3", progress=seen.append)
    with h5py.File(run_file, "r") as f:  # the records the file confirms, per stream, as plain h5py reads them
        counts = dict(zip(json.loads(f["status/samples"].attrs["names"]), f["status/samples"][:], strict=True))
        streams = [s for s in counts if s != "events" and s in f]
        chunks = sum(-(-int(counts[s]) // 20_000) for s in streams if counts[s])
    assert len(seen) == chunks and seen == sorted(seen) and seen[-1] == pytest.approx(1.0)


def _one_line_error(res, target: Path) -> None:  # type: ignore[no-untyped-def]
    lines = res.output.strip().splitlines()
    assert res.exit_code == 2 and len(lines) == 1, res.output
    assert str(target) in lines[0] and "Traceback" not in res.output


@pytest.mark.parametrize("version", ["5", "7.3"])
def test_an_unwritable_mat_target_is_named_in_one_line(run_file: Path, tmp_path: Path, version: str) -> None:
    targets = [tmp_path]  # a folder where the file should go
    if Path("/proc/self").is_dir():
        targets.append(Path("/proc/x.mat"))  # the outside tester's: a folder no file can be created in
    for target in targets:
        res = CliRunner().invoke(app, ["export", str(run_file), "--mat", str(target), "--mat-version", version])
        _one_line_error(res, target)


def test_an_unwritable_csv_target_is_named_in_one_line(run_file: Path, tmp_path: Path) -> None:
    (tmp_path / "taken").write_text("a file, not a folder", encoding="utf-8")
    target = tmp_path / "taken" / "csv"
    res = CliRunner().invoke(app, ["export", str(run_file), "--csv", str(target)])
    _one_line_error(res, target)


@pytest.mark.parametrize("version", ["5", "7.3"])
def test_a_full_disk_names_the_mat_target_and_leaves_no_cut_off_file(run_file: Path, tmp_path: Path, version: str,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import errno

    import scipy.io

    import bench.storage.export as export

    def full(*_args: object, **_kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(scipy.io, "savemat", full)
    monkeypatch.setattr(export, "_char", full)  # v7.3: a write after the streams
    target = tmp_path / "run.mat"
    res = CliRunner().invoke(app, ["export", str(run_file), "--mat", str(target), "--mat-version", version])
    _one_line_error(res, target)
    assert "No space left on device" in res.output and not target.exists()
    assert not list(tmp_path.iterdir())  # nor its temporary


def test_a_csv_folder_holds_one_run_an_export_of_the_same_run_replaces_its_own(run_file: Path,
                                                                                tmp_path: Path) -> None:
    """`bench export --csv out/x` of one run, then of another into the same folder: the first run's CSVs stayed
    beside the second's metadata.json, a folder mixing two runs (found by an outside tester). Refused in one line
    before anything is written; an export of the same run again replaces its files and removes its stale ones."""
    import shutil

    other = tmp_path / "other.h5"
    shutil.copy2(run_file, other)
    with h5py.File(other, "r+") as f:
        f.attrs["run_id"] = "another-run"
    folder = tmp_path / "x"
    res = CliRunner().invoke(app, ["export", str(run_file), "--csv", str(folder)])
    assert res.exit_code == 0, res.output
    before = {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    res = CliRunner().invoke(app, ["export", str(other), "--csv", str(folder)])
    _one_line_error(res, folder)
    with h5py.File(run_file, "r") as f:
        assert f"another run (run_id {f.attrs['run_id']})" in res.output  # the run whose export the folder holds
    assert {p.name: p.stat().st_mtime_ns for p in folder.iterdir()} == before  # nothing written, nothing removed
    # the same run again: its own files replaced; a stream file of its earlier export it no longer writes removed,
    # a file of the user's kept
    meta = json.loads((folder / "metadata.json").read_text(encoding="utf-8"))
    assert set(meta["export_files"]) == set(before)
    meta["export_files"].append("motor.csv")
    (folder / "metadata.json").write_text(json.dumps(meta), encoding="utf-8")
    (folder / "motor.csv").write_text("t [s],position [m]\n", encoding="utf-8")
    (folder / "notes.csv").write_text("mine\n", encoding="utf-8")
    res = CliRunner().invoke(app, ["export", str(run_file), "--csv", str(folder)])
    assert res.exit_code == 0, res.output
    assert "replaced the earlier export of this run" in res.output and "motor.csv" in res.output
    assert sorted(p.name for p in folder.iterdir()) == sorted([*before, "notes.csv"])
    # CSVs of no recognised export (no metadata.json): refused too
    (folder / "metadata.json").unlink()
    res = CliRunner().invoke(app, ["export", str(run_file), "--csv", str(folder)])
    _one_line_error(res, folder)


@pytest.mark.parametrize("version", ["5", "7.3"])
def test_an_existing_mat_file_is_refused_not_replaced(run_file: Path, tmp_path: Path, version: str) -> None:
    """`bench export --mat F` replaced an existing F silently (found by outside testers), where --csv refuses
    another run's folder and `bench fit --export` an existing file. Refused in one line naming it, before anything
    is written (the --csv folder given with it included); the file is left as it was."""
    target = tmp_path / "run.mat"
    target.write_bytes(b"mine")
    res = CliRunner().invoke(app, ["export", str(run_file), "--mat", str(target), "--mat-version", version,
                                   "--csv", str(tmp_path / "csv")])
    _one_line_error(res, target)
    assert "exists; bench export does not overwrite files" in res.output
    assert target.read_bytes() == b"mine" and not (tmp_path / "csv").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mat"]  # no temporary left beside it


def test_a_mat_target_not_named_mat_is_refused_before_anything_is_written(run_file: Path, tmp_path: Path) -> None:
    """`bench export --mat x.csv` wrote a MAT file named x.csv (an outside tester): one line naming the option."""
    target = tmp_path / "x.csv"
    res = CliRunner().invoke(app, ["export", str(run_file), "--mat", str(target), "--csv", str(tmp_path / "csv")])
    assert res.exit_code == 2 and res.output == f"error: --mat {target}: a MATLAB file's name ends in .mat (e.g. " \
        f"{tmp_path / 'x.mat'})\n", res.output
    assert not target.exists() and not (tmp_path / "csv").exists()  # nor the CSV files asked beside it
