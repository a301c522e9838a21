"""``bench protocols list|show|copy`` and ``bench init``: the shipped files, copied verbatim into a lab folder.

In-process and quick; tests/test_package.py runs the same commands from an installed wheel.
"""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bench.cli import app
from bench.protocol.schema import load_protocol
from bench.resources import protocols_dir, rigs_dir, shipped_protocols

ROOT = Path(__file__).resolve().parent.parent
runner = CliRunner()


def _rig_of(protocol: Path) -> Path:
    """The rig file a protocol's ``rig`` names: a path from its folder, else a shipped rig's name (the rig files
    listed by the package's resources, not the resolver under test)."""
    ref = tomllib.loads(protocol.read_text(encoding="utf-8"))["protocol"]["rig"]
    local = (protocol.parent / ref).resolve()
    return local if local.exists() or "/" in ref else (rigs_dir() / f"{ref}.toml").resolve()


@pytest.fixture
def in_tmp(tmp_path: Path) -> Path:
    old = Path.cwd()
    os.chdir(tmp_path)
    yield tmp_path
    os.chdir(old)


def test_the_shipped_files_are_the_repository_files() -> None:
    """One source of truth: bench.data links to the top-level folders (a wheel holds copies)."""
    assert protocols_dir().resolve() == (ROOT / "protocols").resolve()
    assert rigs_dir().resolve() == (ROOT / "rigs").resolve()
    names = {p.relative_to(ROOT / "protocols").with_suffix("").as_posix() for p in (ROOT / "protocols").rglob("*.toml")}
    assert set(shipped_protocols()) == names
    for path in shipped_protocols().values():  # every shipped protocol names a shipped rig
        assert _rig_of(path).is_file() and _rig_of(path).parent == rigs_dir().resolve()


def test_protocols_list_and_show() -> None:
    res = runner.invoke(app, ["protocols", "list", "--json"])
    assert res.exit_code == 0, res.output
    listed = {i["name"]: i for i in json.loads(res.output)}
    assert set(listed) == set(shipped_protocols())
    assert listed["thesis-identification"]["rig"] == "thesis-daq-sim"
    res = runner.invoke(app, ["protocols", "show", "short/thesis-identification-short"])
    assert res.exit_code == 0
    assert res.output == (ROOT / "protocols/short/thesis-identification-short.toml").read_text(encoding="utf-8")
    res = runner.invoke(app, ["protocols", "show", "no-such-protocol"])
    assert res.exit_code == 2 and "no shipped protocol 'no-such-protocol'" in res.output


def test_init_copies_verbatim_and_every_protocol_names_the_labs_rig(in_tmp: Path) -> None:
    res = runner.invoke(app, ["init", "lab"])
    assert res.exit_code == 0, res.output
    lab = in_tmp / "lab"
    for src in (ROOT / "protocols").rglob("*"):
        if src.is_file():
            copy = lab / "protocols" / src.relative_to(ROOT / "protocols")
            assert copy.read_bytes() == src.read_bytes(), copy  # comments and all
    for src in (ROOT / "rigs").glob("*.toml"):
        assert (lab / "rigs" / src.name).read_bytes() == src.read_bytes()
    for copy in (lab / "protocols").rglob("*.toml"):
        assert _rig_of(copy).parent == (lab / "rigs").resolve(), copy
    assert (lab / "runs").is_dir() and (lab / "README.md").is_file()
    (lab / "rigs" / "thesis-daq-sim.toml").write_text("# edited\n", encoding="utf-8")
    res = runner.invoke(app, ["init", "lab"])
    assert res.exit_code == 2 and "does not overwrite" in res.output
    assert (lab / "rigs" / "thesis-daq-sim.toml").read_text(encoding="utf-8") == "# edited\n"


@pytest.mark.parametrize("dest", ["protocols/mine.toml", "protocols/short/mine.toml", "protocols/a/b/mine.toml"])
def test_copy_into_a_lab_folder_names_the_labs_rig(in_tmp: Path, dest: str) -> None:
    assert runner.invoke(app, ["init", "lab"]).exit_code == 0
    (in_tmp / "lab" / Path(dest).parent).mkdir(parents=True, exist_ok=True)
    res = runner.invoke(app, ["protocols", "copy", "thesis-identification", f"lab/{dest}"])
    assert res.exit_code == 0, res.output
    assert "note:" not in res.output  # the lab's own rig: nothing to say
    copy = in_tmp / "lab" / dest
    assert _rig_of(copy) == (in_tmp / "lab" / "rigs" / "thesis-daq-sim.toml").resolve()
    rig_line = next(line for line in copy.read_text(encoding="utf-8").splitlines() if line.startswith("rig ="))
    assert not Path(tomllib.loads(rig_line)["rig"]).is_absolute()  # the lab folder can move
    original = (ROOT / "protocols" / "thesis-identification.toml").read_text(encoding="utf-8").splitlines()
    assert [line for line in copy.read_text(encoding="utf-8").splitlines() if not line.startswith("rig =")] == \
        [line for line in original if not line.startswith("rig =")]  # comments and layout kept


def test_copy_outside_a_lab_names_the_shipped_rig_and_validates(in_tmp: Path) -> None:
    res = runner.invoke(app, ["protocols", "copy", "short/thesis-identification-short", "mine.toml"])
    assert res.exit_code == 0, res.output
    # by name, not by an absolute site-packages path (outside tester: it broke when bench was reinstalled), and
    # said, with where to get one's own
    note = next(line for line in res.output.splitlines() if line.startswith("note: its rig = "))
    assert "note: its rig = thesis-daq-sim is the rig of that name shipped with bench" in note
    assert "bench init LAB" in note and "--rig" in note
    assert tomllib.loads((in_tmp / "mine.toml").read_text(encoding="utf-8"))["protocol"]["rig"] == "thesis-daq-sim"
    assert _rig_of(in_tmp / "mine.toml") == (rigs_dir() / "thesis-daq-sim.toml").resolve()
    res = runner.invoke(app, ["validate", "mine.toml", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["valid"] is True
    res = runner.invoke(app, ["protocols", "copy", "thesis-identification", "mine.toml"])
    assert res.exit_code == 2 and "exists" in res.output


def test_a_protocol_names_a_shipped_rig_by_name_and_an_unknown_name_is_a_missing_file(in_tmp: Path) -> None:
    """``rig = "thesis-sim"`` (no folder, no .toml) is the rig of that name shipped with bench, from any folder; a
    file of that name beside the protocol comes first; an unknown name is refused as the missing file it names."""
    text = (ROOT / "protocols" / "short" / "thesis-identification-short.toml").read_text(encoding="utf-8")
    body = "\n".join(line for line in text.splitlines() if not line.startswith("rig ="))
    (in_tmp / "p.toml").write_text(body.replace("[protocol]", '[protocol]\nrig = "thesis-sim"', 1), encoding="utf-8")
    res = runner.invoke(app, ["validate", "p.toml", "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["valid"] is True, res.output
    assert load_protocol(in_tmp / "p.toml").rig_path() == (rigs_dir() / "thesis-sim.toml").resolve()
    (in_tmp / "thesis-sim").write_text((ROOT / "rigs" / "thesis-sim.toml").read_text(encoding="utf-8"),
                                       encoding="utf-8")  # a file of that name beside it: the file
    assert load_protocol(in_tmp / "p.toml").rig_path() == (in_tmp / "thesis-sim").resolve()
    (in_tmp / "q.toml").write_text(body.replace("[protocol]", '[protocol]\nrig = "no-such-rig"', 1),
                                   encoding="utf-8")
    res = runner.invoke(app, ["validate", "q.toml"])
    assert res.exit_code == 2 and "no-such-rig" in res.output and "not found" in res.output, res.output
    # a misspelt name: the file and its field named, the rig meant suggested (outside tester: only the path was)
    (in_tmp / "t.toml").write_text(body.replace("[protocol]", '[protocol]\nrig = "thesis-sm"', 1), encoding="utf-8")
    res = runner.invoke(app, ["validate", "t.toml"], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and res.output.count("\n") == 1, res.output
    assert res.output.startswith("error: protocol file ") and "t.toml: protocol.rig = 'thesis-sm': rig file " in \
        res.output and "did you mean thesis-sim?" in res.output, res.output


def test_a_shipped_protocols_name_runs_from_any_folder_and_a_misspelt_one_is_suggested(in_tmp: Path) -> None:
    """`bench validate thesis-identification` (a name `bench protocols list` shows) said "not found" outside the
    repository (outside tester): a shipped protocol's name is that protocol, from any folder; a misspelt one is
    refused with the name meant; a local file of that name comes first."""
    res = runner.invoke(app, ["validate", "short/thesis-identification-short", "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["protocol"] == "thesis-identification-short", res.output
    res = runner.invoke(app, ["validate", "thesis-identificaton"], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and res.output == ("error: protocol file thesis-identificaton: not found; did you "
                                                 "mean the shipped protocol thesis-identification?\n"), res.output
    text = (protocols_dir() / "short" / "thesis-identification-short.toml").read_text(encoding="utf-8")
    (in_tmp / "thesis-identification.toml").write_text(text.replace("../../rigs/thesis-daq-sim.toml",
                                                                     "thesis-sim"), encoding="utf-8")
    res = runner.invoke(app, ["validate", "thesis-identification", "--json"])  # the file here, not the shipped one
    assert res.exit_code == 0 and json.loads(res.output)["protocol"] == "thesis-identification-short", res.output
    # in the repository, protocols/ is the shipped folder itself: no lab copy to choose over (the demo's closing
    # line, `bench run thesis-voltage-sweep`, was refused there)
    os.chdir(ROOT)
    assert (ROOT / "protocols" / "thesis-voltage-sweep.toml").resolve() == \
        (protocols_dir() / "thesis-voltage-sweep.toml").resolve()
    res = runner.invoke(app, ["validate", "thesis-voltage-sweep", "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["protocol"] == "thesis-voltage-sweep", res.output


def test_a_lab_folders_own_copy_is_never_passed_over_for_the_shipped_one_of_its_name(in_tmp: Path) -> None:
    """A reviewer: in a lab folder whose protocols/thesis-voltage-sweep.toml was edited, `bench validate
    thesis-voltage-sweep` planned the shipped protocol without a word (and `--rig thesis-sim` from protocols/ the
    shipped rig, not ../rigs/thesis-sim.toml). The name is refused, naming the lab's copy; a path runs it."""
    assert runner.invoke(app, ["init", "lab"]).exit_code == 0
    os.chdir(in_tmp / "lab")
    res = runner.invoke(app, ["validate", "thesis-voltage-sweep"], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and res.output == ("error: protocol file thesis-voltage-sweep: not found; did you mean "
                                                 "protocols/thesis-voltage-sweep.toml (this lab folder's copy)?\n"), \
        res.output
    os.chdir(in_tmp / "lab" / "protocols")
    res = runner.invoke(app, ["validate", "thesis-voltage-sweep.toml", "--rig", "thesis-sim"], env={"COLUMNS": "300"})
    assert res.exit_code == 2 and "did you mean ../rigs/thesis-sim.toml?" in res.output, res.output
    res = runner.invoke(app, ["validate", "thesis-voltage-sweep.toml", "--rig", "../rigs/thesis-sim.toml"])
    assert res.exit_code == 0, res.output
