"""What an armed stream is: the plan the device will follow, and the driver's running state of it."""

from __future__ import annotations

import math
import socket
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from drivers.interfaces import StreamSpec
from drivers.labjack.looping import Loop
from drivers.labjack.registers import OUT_PACKET_VALUES

if TYPE_CHECKING:
    from drivers.labjack.packets import StreamBatch


@dataclass
class StreamPlan:
    """What the device will do: actual scan rate, scan list, and the stream-out codes it will play."""

    scan_rate: float
    dt: float
    names: tuple[str, ...]
    scan_list: tuple[int, ...]
    samples_per_packet: int
    out_codes: np.ndarray | None
    out_volts: np.ndarray | None  # what the 12-bit DAC outputs for out_codes
    out_capacity: int  # values the stream-out buffer holds
    max_collect_interval: float  # call collect at least this often [s] so the out buffer never runs dry
    out_ahead: int = 0  # values kept in the device at most, ahead of the last scan received (≤ out_capacity)
    out_chunk: int = OUT_PACKET_VALUES  # a top-up waits until this many values fit (or the rest of the data)



@dataclass
class StreamState:
    """An armed stream as the driver follows it: its plan, socket, scan clock, packets and stream-out progress."""

    plan: StreamPlan
    spec: StreamSpec
    n_in: int
    gains: tuple[int, ...]
    sock: socket.socket | None = None
    t_enable: float = 0.0
    t0: float = 0.0
    t0_uncertainty: float = math.nan
    next_tid: int = 0
    raw: bytearray = field(default_factory=bytearray)
    pending: list[int] = field(default_factory=list)  # samples of a scan split across packets
    # packets received and parsed (their numbers taken) but not yet handed out: a receive that a stop request, a
    # timeout or a lost packet ended keeps them here for the next collect, which numbers their scans
    received: list[StreamBatch] = field(default_factory=list)
    scans: int = 0  # scan index of the next scan to hand out (skipped ones included)
    packets: int = 0
    out_written: int = 0
    out_base: int = 0  # index of plan.out_codes[0] among every value given (extend drops written ones)
    out_closed: bool = True  # no values will be appended: the hold loop follows the last one
    out_final: bool = False  # the hold loop is written: the device plays nothing more from the host
    underrun_scans: int = 0
    done: bool = False
    loop: Loop | None = None  # a looped stretch planned or playing (:mod:`.looping`)
    looping: bool = False  # its block is in the device and repeats: the host writes nothing until it leaves it
    loop_searched: tuple[int, int] = (-1, -1)  # (first value, values given) of the last search for a loop

