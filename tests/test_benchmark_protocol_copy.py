"""The benchmarks' protocol copies (bench.benchmarks.copy_protocol): a copy in another folder finds its rig."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bench.benchmarks import copy_protocol
from bench.resources import protocols_dir
from bench.runtime.run import plan_run

SOURCE = protocols_dir() / "short" / "thesis-identification-short.toml"  # 10 s of drive, 1 s of rest (the file)


def test_a_copy_elsewhere_plans_on_the_source_rig_with_its_edit(tmp_path: Path) -> None:
    def shorter(doc: Any) -> None:
        doc["steps"][0]["duration_s"] = 2.0

    copy = copy_protocol(SOURCE, tmp_path / "copy.toml", shorter)
    assert copy.parent == tmp_path  # the source's relative rig path ("../../rigs/…") would not resolve from here
    source, copied = plan_run(SOURCE), plan_run(copy)
    assert copied.rig.name == source.rig.name == "thesis-daq-sim"
    assert source.program.duration == 11.0 and copied.program.duration == 3.0
