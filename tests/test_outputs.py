"""Output files (bench/storage/outputs.py): a replaced run output keeps the permissions it had, and a long file
name still gets its temporary file beside it."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from bench.storage.outputs import write_text


@pytest.mark.skipif(os.name != "posix", reason="POSIX permission bits")
def test_a_replaced_output_keeps_its_permissions(tmp_path: Path) -> None:
    target = tmp_path / "run-report.md"
    target.write_text("old")
    target.chmod(0o640)  # a lab's group-readable report
    write_text(target, "new", replace=True)
    assert target.read_text() == "new" and stat.S_IMODE(target.stat().st_mode) == 0o640


def test_a_long_file_name_is_written(tmp_path: Path) -> None:
    target = tmp_path / ("x" * 240 + ".csv")  # 244 characters: within the usual 255-byte name limit
    write_text(target, "a,b\n")
    assert target.read_text() == "a,b\n" and [p.name for p in tmp_path.iterdir()] == [target.name]
