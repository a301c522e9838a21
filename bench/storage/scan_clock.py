"""The ``timing`` event a hardware-timed stream's kickoff writes: its text's grammar, written and read here only.

``DAQ scan clock: scan 0 at <t> s on the run clock, known to <u> ms (the enable request's round trip)``, then either
``; polled channels (motor encoder) are timestamped on the same run clock`` — a step's own stream, whose scan 0 plays
that step's start — or ``: <what>`` — a stream of the engine's own (a ramp's, the inputs after 0 V). Every file
written since the DAQ rigs came carries it (so old files read alike); the writer is
:mod:`bench.runtime.hardware_timed`, the readers :meth:`bench.storage.runfile.RunFile.step_offsets` (the analysis's
cycles on the scan clock) and :mod:`bench.runtime.replay` (a replayed record's streams).
"""

from __future__ import annotations

import re

KIND = "timing"  # the event's kind
STEP_STREAM = "polled channels (motor encoder) are timestamped on the same run clock"
_OWN = "; polled channels"  # what marks a step's own stream (its shortest form: every file's text has it)
_KICKOFF = re.compile(r"DAQ scan clock: scan 0 at (-?[\d.]+) s on the run clock")


def kickoff_text(t: float, uncertainty_s: float, what: str | None = None) -> str:
    """The event's text for a stream whose scan 0 is at run time ``t`` [s], known to ``uncertainty_s``: a step's own
    stream (``what`` None) or one of the engine's (``what`` says what for)."""
    head = (f"DAQ scan clock: scan 0 at {t:.6f} s on the run clock, known to {uncertainty_s * 1e3:.3f} ms (the enable "
            "request's round trip)")
    return f"{head}; {STEP_STREAM}" if what is None else f"{head}: {what}"


def parse_kickoff(text: str) -> tuple[float, bool] | None:
    """(scan 0's run time [s], whether the stream is a step's own) of a kickoff's text; None for any other text."""
    m = _KICKOFF.match(text)
    return None if m is None else (float(m[1]), _OWN in text)
