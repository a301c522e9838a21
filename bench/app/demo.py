"""Use case: the demo's run — the thesis identification protocol on the simulated rig in virtual time (``bench
demo``, which then fits the recorded file with :mod:`bench.app.fit` and reports it with :mod:`bench.app.analysis`)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from bench.runtime.engine import RunResult
    from bench.runtime.run import Plan

DEMO_PROTOCOL = "thesis-identification"  # shipped: 7 kV raised cosine at 1/9 Hz, 296 K, laser at 10 kHz


def plan_demo() -> Plan:
    """Validate and dry-run the shipped thesis identification protocol on its (simulated) rig."""
    from bench.resources import protocol
    from bench.runtime.run import plan_run

    return plan_run(protocol(DEMO_PROTOCOL))


def run_demo(plan: Plan, out: Path) -> RunResult:
    """Run the planned demo on the simulated rig in virtual time (the same bytes on the wire), into ``out``."""
    from bench.runtime.run import default_output, execute

    return execute(plan, default_output(plan, out), virtual=True)
