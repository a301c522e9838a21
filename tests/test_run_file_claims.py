"""A run's file is its own: two runs started in one second into one folder write two files, a run file is never
overwritten, and one campaign is continued by one resumed run at a time (found from outside: two `bench run` in
the same second both printed one file name and one run's data was lost; two `--resume` of one file forked it)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.app.runs import prepare_run
from bench.runtime.engine import Engine
from bench.runtime.rig_lock import LOCK_DIR_ENV, campaign_claimed
from bench.runtime.run import execute, plan_resume, plan_run, reserve_output
from bench.storage.runfile import open_run

ROOT = Path(__file__).resolve().parents[1]
IDENT = ROOT / "protocols" / "short" / "thesis-identification-short.toml"
SWEEPS = ROOT / "protocols" / "short" / "thesis-sweeps-short.toml"


@pytest.fixture(autouse=True)
def _locks(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(LOCK_DIR_ENV, str(tmp_path / "locks"))
    (tmp_path / "locks").mkdir()


def test_two_runs_named_in_one_second_write_two_files(tmp_path: Path) -> None:
    out = tmp_path / "runs"
    first, second = (prepare_run(IDENT, out=out) for _ in range(2))  # both planned before either starts
    if first.path != second.path:
        pytest.skip("the two plans fell into different seconds: the race needs one name")
    a, b = reserve_output(first.path), reserve_output(second.path)
    assert a == first.path and b != a and b.parent == a.parent  # the second claims the next name
    assert a.with_suffix(".log").exists() and b.with_suffix(".log").exists()
    runs = [execute(p.plan, path, virtual=True, metadata=p.metadata) for p, path in ((first, a), (second, b))]
    assert [r.state for r in runs] == ["completed", "completed"]
    ids = {open_run(r.path, streams=False).attrs["run_id"] for r in runs}
    assert len(ids) == 2  # two runs, two files, both whole


def test_a_name_taken_by_a_file_or_a_log_is_skipped(tmp_path: Path) -> None:
    path = tmp_path / "p-20261127-120000.h5"
    path.write_bytes(b"")  # a run file (or one a copy put there)
    (tmp_path / "p-20261127-120000-1.log").write_text("")  # another run's claim: its log
    assert reserve_output(path) == tmp_path / "p-20261127-120000-2.h5"


def test_an_existing_file_is_never_overwritten(tmp_path: Path) -> None:
    target = tmp_path / "taken.h5"
    target.write_bytes(b"someone's data")
    with pytest.raises(Exception, match="never overwritten") as err:
        execute(plan_run(IDENT), target, virtual=True)
    assert str(target) in str(err.value) and "\n" not in str(err.value)
    assert target.read_bytes() == b"someone's data"


def test_one_continuation_of_a_campaign_at_a_time(tmp_path: Path) -> None:
    def stop_at_once(engine: Engine, _sim: object) -> None:
        engine.request_stop("stopped by the test")

    first = execute(plan_run(SWEEPS), tmp_path / "first.h5", virtual=True, on_engine=stop_at_once)
    assert first.state != "completed"
    plan, link, _ = plan_resume(first.path)  # planned by two processes at once: both passed the resumed check
    with campaign_claimed(first.path), pytest.raises(ValueError, match="being resumed by process"):
        execute(plan, tmp_path / "second.h5", virtual=True, resume=link)
    assert not (tmp_path / "second.h5").exists()
    second = execute(plan, tmp_path / "second.h5", virtual=True, resume=link)
    assert second.state == "completed", second.reason
    with pytest.raises(ValueError, match=r"already resumed in .*second\.h5"):  # the other, planned before it ran
        execute(plan, tmp_path / "third.h5", virtual=True, resume=link)
    assert not (tmp_path / "third.h5").exists()


def test_a_resume_into_another_folder_is_refused_before_anything_is_done(tmp_path: Path) -> None:
    """A continuation is looked for beside the campaign's latest file: a resume written elsewhere (--out) was not
    found by the next resume, and the campaign forked (found in review). Refused, naming the folder it belongs in."""
    def stop_at_once(engine: Engine, _sim: object) -> None:
        engine.request_stop("stopped by the test")

    (tmp_path / "a").mkdir()
    first = execute(plan_run(SWEEPS), tmp_path / "a" / "first.h5", virtual=True, on_engine=stop_at_once)
    with pytest.raises(ValueError, match=r"--out .*b: a resumed campaign is written beside its latest file"):
        prepare_run(None, resume=Path(first.path), out=tmp_path / "b")
    assert not (tmp_path / "b").exists()
    here = prepare_run(None, resume=Path(first.path), out=tmp_path / "a", dry_run=True)  # its own folder: fine
    assert here.path.parent == tmp_path / "a"
