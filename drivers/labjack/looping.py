"""Stream-out looping: where a waveform repeats, so that the T7 can play it from its buffer ([D] register map:
STREAM_OUT#_LOOP_NUM_VALUES, "the number of values, from the end of the array, that will be repeated after
reaching the end of supplied data array"; STREAM_OUT#_SET_LOOP 1 "use new data immediately"; LabJack's stream-out
update example: a loop set with SET_LOOP "will not be interrupted until [its] loop is complete", then the next data
plays — T-Series Datasheet §3.2.1 Stream-Out, "read in a looping mode to generate a periodic waveform").

The search works on the DAC codes themselves: a run repeats only where the codes the T7 would play are equal
value for value, so a looped drive plays exactly the codes a refilled one plays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WINDOW = 16  # values compared at once to find candidate periods


@dataclass(frozen=True)
class Loop:
    """A looped stretch of a stream-out: the ``block`` values from value ``at`` on (whole periods) play
    ``blocks`` times in a row — the first time as written data, then as the device's repetitions."""

    at: int
    block: int
    blocks: int

    @property
    def end(self) -> int:
        """Index of the first value after the repetitions."""
        return self.at + self.block * self.blocks


def periodic_run(codes: np.ndarray, max_period: int) -> tuple[int, int]:
    """(P, n): a period P ≤ ``max_period`` with which ``codes`` repeat from their start, and the length n ≥ 2P of
    that run (codes[k + P] == codes[k] for k < n − P); (0, 0) when there is none. P is the smallest of the first
    eight candidates (offsets where the first :data:`WINDOW` codes recur): the smallest period where it is among
    them (always, for a waveform whose first codes do not recur within one period)."""
    n = codes.size
    w = min(WINDOW, n // 2)
    lim = min(max_period, n - w)
    if w < 1 or lim < 1:
        return 0, 0
    # the offsets where the first code recurs, then those of them where the whole window does (in offset order)
    at = np.flatnonzero(codes[1:lim + 1] == codes[0]) + 1
    rows = codes[at[:, None] + np.arange(w)]
    for p in at[(rows == codes[:w]).all(axis=1)][:8]:
        p = int(p)
        run = p + _agree(codes, p)
        if run >= 2 * p:
            return p, run
    return 0, 0


def _agree(codes: np.ndarray, p: int) -> int:
    """How many codes from the start equal those ``p`` later (the first k with codes[p + k] != codes[k], or all
    n − p): compared in stretches that double, so a candidate that fails early costs little."""
    m = codes.size - p
    k, step = 0, 4096
    while k < m:
        e = min(k + step, m)
        diff = np.flatnonzero(codes[p + k:p + e] != codes[k:e])
        if diff.size:
            return k + int(diff[0])
        k, step = e, 2 * step
    return m


def plan_loop(codes: np.ndarray, at: int, min_block: int, max_block: int, min_blocks: int = 4) -> Loop | None:
    """A loop for ``codes`` (the values from index ``at`` on): whole periods in a block of at least ``min_block``
    and at most ``max_block`` values (the buffer must hold it and the data after it), repeated at least
    ``min_blocks`` times — else None (refilling costs as little)."""
    p, run = periodic_run(codes, max_block)
    if not p:
        return None
    block = p * -(-min_block // p)
    if block > max_block or run // block < min_blocks:
        return None
    return Loop(at, block, run // block)
