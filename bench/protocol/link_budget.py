"""Link budget of a compiled program on its rig: can each wire carry what the engine will ask of it?

For every link the engine uses — each Modbus RTU bus (also behind a TCP gateway: the RS-485 line is the
bottleneck), the LK-G RS-232 link, the LinRS link — the load is Σ (transactions/s × time on the wire), the
time of one transaction being its characters (8N1: 10 bits each) at the link's baud rate, the inter-frame
silences (Modbus RTU: 3.5 characters, 1.75 ms above 19200 Bd — Modbus over Serial Line v1.02 §2.5.1.1)
and the device's turnaround. Besides the load: the laser's storage fill rate against its upload rate (the
engine uploads while it stores), and polling rates against the instruments' conversion rates.

**The host waits on one link at a time.** The engine runs every transaction of a step from one thread and waits
for each reply before the next request (a set-point tick sends the amplifier's FC6 *and* the motor's go-to, then
the due polls), so the links' loads add up: three links each busy 30–70 % of the time keep one host busy more than
all of it, and its software-timed schedule falls behind although no single wire is full. :func:`check_links`
therefore also checks the sum over every serial link, the laser's storage upload included (fetched while the step
stores: its share of the time is the storage rate over :func:`laser_upload_rate`).

:func:`check_links` returns one line per problem, naming the channel, the numbers and what would fit;
an empty list means every link can carry the program. The traffic model follows :mod:`bench.runtime.engine`:
set-points at ``recording.setpoint_Hz`` while a step streams, then one keep-alive per
``max(1/setpoint_Hz, HOLD_KEEPALIVE_S)``; monitors, encoder and load cell at their rates; laser storage
fetched every ``FETCH_PERIOD_S`` while storing (each fetch bounded by the step's next action, the rest on the
following ticks), single reads at ``PASSIVE_LASER_HZ`` otherwise. What a storing step drains is not a share of
the wire but what the engine's fetches carry: :func:`laser_drain_rate` replays the step's schedule — the fetch
poll, each fetch ending at the next set-point *or poll*, the driver's per-call budget — over its repeat.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from fractions import Fraction

from bench.protocol.program import (
    DRAIN_HOLD_S,
    FETCH_PERIOD_S,
    HOLD_KEEPALIVE_S,
    PASSIVE_LASER_HZ,
    Program,
    Segment,
    voltage_at,
)

TURNAROUND_MODBUS_S = 1e-3  # ADAM / DGT1S request → reply [assumed: no figure in the manuals read]
TURNAROUND_LKG_S = 0.5e-3  # LK-G command → reply [assumed]
TURNAROUND_LINRS_S = 1e-3  # LinMot telegram → response [assumed]
ADAM_4017P_RATE = 10.0  # conversions/s over all enabled channels (datasheet)
DGT1S_RATE = 100.0  # conversions/s [assumed: the DGT1S offers several rates]
LKG_VALUE_BYTES = 9  # one stored value in an AO reply: 8 characters and a comma (manual p. 5-6)
# the driver's (drivers.keyence, which this layer may not import; tests/test_laser_drain_rate.py compares them):
LKG_UPLOAD_CHUNK_S = 0.2  # FETCH_BUDGET_S: AO requests sized to this much wire time, and one fetch call's budget
LKG_EXCHANGE_ALLOWANCE_S = 2e-3  # EXCHANGE_ALLOWANCE_S: a bounded fetch's allowance per exchange beyond its characters
LKG_FETCH_OVERHEAD_BYTES = 16 + 3 + 3 + 16  # FETCH_OVERHEAD_BYTES: the AN status exchange and an AO request's head
COLLECT_PERIOD_S = 0.05  # bench.runtime.polls' COLLECT_PERIOD_S: a DAQ stream's collect on hardware
DRAIN_SPAN_S = 10.0  # laser_drain_rate: the longest schedule repeat replayed
MAX_LOAD = 1.0  # a link busy more than this fraction of the time cannot keep up


Polls = tuple[tuple[float, float], ...]  # (polls/s, seconds of the host's time each)


@dataclass(frozen=True)
class LinkLoad:
    """What one link carries: name, baud rate, busiest-step traffic and its share of the wire."""

    link: str
    baud: int
    items: tuple[tuple[str, float, float], ...]  # (channel, transactions/s, seconds per transaction)

    @property
    def load(self) -> float:
        """Fraction of the time the wire is busy."""
        return sum(rate * t for _, rate, t in self.items)


def char_time(baud: int) -> float:
    """Seconds per character, 8N1."""
    return 10.0 / baud


def rtu_transaction(baud: int, request: int, reply: int) -> float:
    """Wire time of one Modbus RTU transaction: both frames, two end-of-frame silences, turnaround."""
    gap = 1.75e-3 if baud > 19200 else 3.5 * char_time(baud)
    return (request + reply) * char_time(baud) + 2 * gap + TURNAROUND_MODBUS_S


def _streaming_rate(program: Program) -> float:
    """Set-points per second in the busiest step (streaming at setpoint_Hz, else keep-alives)."""
    rec = program.protocol.recording
    dt = 1.0 / rec.setpoint_Hz
    best = 0.0
    for seg in program.segments:
        if seg.duration <= 0:
            continue
        rate = rec.setpoint_Hz if seg.stream_until > seg.t_start else 1.0 / max(dt, HOLD_KEEPALIVE_S)
        best = max(best, rate)
    return best


def _hardware_timed(program: Program) -> tuple[bool, bool]:
    """(set-points, laser) through a hardware-timed DAQ instead of the serial links."""
    rig = program.rig
    daq = getattr(rig, "daq", None)
    amp_daq = rig.amplifier is not None and getattr(rig.amplifier, "drive", "adam") == "daq"
    laser_daq = daq is not None and getattr(daq, "laser_ain", None) is not None
    return amp_daq, laser_daq


def link_loads(program: Program) -> list[LinkLoad]:
    """The load of every serial link of the rig in the program's busiest step."""
    rig, rec = program.rig, program.protocol.recording
    amp_daq, laser_daq = _hardware_timed(program)
    setpoints = _streaming_rate(program)
    buses: dict[str, list[tuple[str, float, float]]] = {}
    if (a := rig.amplifier) is not None and not amp_daq:
        baud = rig.buses[a.bus].baudrate
        n = abs(a.vmon_channel - a.imon_channel) + 1
        buses.setdefault(a.bus, []).append(("amplifier set-points (FC6, ADAM-4024)", setpoints,
                                            rtu_transaction(baud, 8, 8)))
        if rec.monitors_Hz:
            buses[a.bus].append(("amplifier monitors (FC3, ADAM-4017+)", rec.monitors_Hz,
                                 rtu_transaction(baud, 8, 5 + 2 * n)))
    if (c := rig.load_cell) is not None and rec.force_Hz:
        baud = rig.buses[c.bus].baudrate
        buses.setdefault(c.bus, []).append(("load cell (FC4, DGT1S)", rec.force_Hz, rtu_transaction(baud, 8, 15)))
    out = [LinkLoad(f"bus {name}", rig.buses[name].baudrate, tuple(items)) for name, items in buses.items()]
    if (m := rig.motor) is not None:
        ct = char_time(m.baudrate)
        items = []
        if rec.position_Hz:
            items.append(("motor position (LinRS default response)", rec.position_Hz,
                          (7 + 16) * ct + TURNAROUND_LINRS_S))
        if program.has_motor_axis and any(s.position is not None for s in program.segments):
            items.append(("motor set-points (LinRS VAI go-to)", setpoints, (25 + 16) * ct + TURNAROUND_LINRS_S))
        out.append(LinkLoad("motor", m.baudrate, tuple(items)))
    if (lz := rig.laser) is not None and not laser_daq:
        ct = char_time(lz.baudrate)
        out.append(LinkLoad("laser", lz.baudrate, (("laser single reads (M1/MS)", PASSIVE_LASER_HZ,
                                                     (6 + 15) * ct + TURNAROUND_LKG_S),)))
    return out


def _streaming_step(program: Program) -> str:
    """The step whose set-points load the links most: the first that streams go-tos to the motor, else the first
    that streams at ``setpoint_Hz`` (else the first step)."""
    streaming = [s for s in program.segments if s.duration > 0 and s.stream_until > s.t_start]
    moving = [s for s in streaming if s.position is not None]
    seg = (moving or streaming or list(program.segments))[0]
    return seg.label.rsplit("/", 1)[-1]  # the innermost step of a sweep: its name and its path


def _check_host(program: Program, links: list[LinkLoad], upload: float = 0.0) -> str | None:
    """One line if the links' loads together exceed the host's time (see the module's docstring); ``upload``: the
    share of the time the laser's storage upload holds the host while a step stores (it is fetched in the step)."""
    total = sum(link.load for link in links) + upload
    if total <= MAX_LOAD or len([link for link in links if link.items]) + (upload > 0) < 2:
        return None  # one link alone: its own line says it
    rec = program.protocol.recording
    per_setpoint = sum(t for link in links for ch, _, t in link.items if "set-points" in ch)
    setpoint_load = sum(rate * t for link in links for ch, rate, t in link.items if "set-points" in ch)
    shares = ", ".join([f"{link.link} {link.load:.0%}" for link in links if link.items]
                       + ([f"laser storage upload {upload:.0%}"] if upload > 0 else []))
    room = (MAX_LOAD * 0.9 - (total - setpoint_load)) / per_setpoint if per_setpoint > 0 else 0.0
    fit = (f"lower recording.setpoint_Hz to ≤ {int(room)}" if room >= 1 else
           "lower the polling rates (recording.force_Hz, position_Hz, monitors_Hz"
           + (", displacement_Hz" if upload > 0 else "") + ")") + " (or a hardware-timed drive)"
    return (f"host at recording.setpoint_Hz = {rec.setpoint_Hz:g}: step {_streaming_step(program)} keeps the host "
            f"on the wire {total:.0%} of the time ({shares}; the engine waits on one link at a time), so its "
            f"schedule would fall behind; {fit}")


def _upload_chunk(baud: int) -> int:
    """Values per AO request: LKG_UPLOAD_CHUNK_S of wire time (as the driver sizes them), 1–1000."""
    return max(1, min(1000, int(LKG_UPLOAD_CHUNK_S / (LKG_VALUE_BYTES * char_time(baud)))))


def laser_fetch_time(baud: int, points: int) -> float:
    """Seconds one upload of ``points`` stored values takes on the RS-232 line: AO requests of
    :func:`_upload_chunk` values, each with its AN status query, request echo and turnarounds."""
    ct = char_time(baud)
    requests = -(-points // _upload_chunk(baud))
    return requests * ((16 + 3 + 3 + 16) * ct + 2 * TURNAROUND_LKG_S) + points * LKG_VALUE_BYTES * ct


def laser_upload_rate(baud: int) -> float:
    """Stored values per second an RS-232 upload carries (:func:`laser_fetch_time` of full AO requests)."""
    n = _upload_chunk(baud)
    return n / laser_fetch_time(baud, n)


def check_links(program: Program) -> list[str]:
    """One line per link the program would overload (empty: every link carries it)."""
    rig, rec = program.rig, program.protocol.recording
    problems: list[str] = []
    loads = link_loads(program)
    for link in loads:
        if link.load > MAX_LOAD:
            parts = ", ".join(f"{ch} {rate:g}/s × {t * 1e3:.1f} ms" for ch, rate, t in link.items)
            fit = _fit_setpoints(link)
            problems.append(f"{link.link} at {link.baud} Bd: busy {link.load:.0%} of the time ({parts}); {fit}")
    amp_daq, laser_daq = _hardware_timed(program)
    storing = (lz := rig.laser) is not None and not laser_daq and any(s.storing for s in program.segments)
    stored = program.laser_Hz  # as the controller stores it, not as asked (800 S/s asked: 1000 stored)
    upload_share = stored / laser_upload_rate(lz.baudrate) if storing and lz is not None else 0.0
    if storing and lz is not None:
        upload = laser_upload_rate(lz.baudrate)
        if stored > upload:
            longest = max(s.duration for s in program.segments if s.storing)
            points = longest * stored
            problems.append(
                f"laser at {lz.baudrate} Bd: storage fills at {stored:,.0f} S/s but the link uploads "
                f"at most {upload:,.0f} S/s while it records (9 bytes a value); lower recording.displacement_Hz "
                f"to ≤ {int(upload * 0.9):,} or store each step and upload between steps (longest step "
                f"{longest:g} s = {points:,.0f} points, {points / upload:,.0f} s of upload)")
        if (line := _check_upload_hold(program, lz.baudrate)) is not None:
            problems.append(line)
    if rig.amplifier is not None and not amp_daq and rec.monitors_Hz:
        per_channel = ADAM_4017P_RATE / 2  # V and I monitors enabled: round robin over two channels
        if rec.monitors_Hz > per_channel:
            problems.append(f"amplifier monitors: polled at {rec.monitors_Hz:g}/s but the ADAM-4017+ converts "
                            f"{ADAM_4017P_RATE:g} S/s over 2 channels ({per_channel:g} S/s each): most reads "
                            f"repeat a value; lower recording.monitors_Hz to ≤ {per_channel:g}")
    if rig.load_cell is not None and rec.force_Hz > DGT1S_RATE:
        problems.append(f"load cell: polled at {rec.force_Hz:g}/s but the DGT1S converts {DGT1S_RATE:g} S/s; "
                        f"lower recording.force_Hz to ≤ {DGT1S_RATE:g}")
    if (host := _check_host(program, loads, upload_share)) is not None:  # last: the links' own lines say what to change
        problems.append(host)
    return problems


def upload_hold(program: Program, on_V: float) -> str | None:
    """One line (a warning: nothing is refused) where steps that store laser data end with the output on (|V| above
    ``on_V``) on a rig whose host sets the voltage: each one's last stored values upload after it, the output held at
    its end value meanwhile — the engine's drain, at most ``DRAIN_HOLD_S``, then ramped to 0 V and the next step
    restarted — time at high voltage the protocol does not ask for (an outside tester: 3 kV held 1.18 s before a
    relax on a loaded host, the dry run silent). The time said: the values one fetch period stores (fewer where the
    step ends within a period) and the backlog a link slower than the storage leaves, at the rate the engine uploads
    while a step runs (:func:`step_drain_rate`: its polls between uploads counted); a host that fell behind adds
    to it."""
    rig = program.rig
    amp_daq, laser_daq = _hardware_timed(program)
    if rig.laser is None or rig.amplifier is None or amp_daq or laser_daq:
        return None
    held, volts = [], 0.0
    for seg in program.segments:
        volts = end if (end := voltage_at(seg, seg.t_end)) is not None else volts
        if seg.storing and seg.duration > 0 and abs(volts) > on_V:
            held.append((seg, volts))
    if not held:
        return None
    stored, loads = program.laser_Hz, link_loads(program)
    tick = min(FETCH_PERIOD_S, 1.0 / program.protocol.recording.setpoint_Hz)

    def tail(seg: Segment) -> float:  # one fetch period's values and the backlog, at the rate the engine uploads
        rate = step_drain_rate(program, seg, loads=loads)  # (its polls between uploads counted, as in the step)
        points = math.ceil(stored * tick + max(0.0, stored - rate) * seg.duration)
        return points / rate if rate > 0 else math.inf

    seg, volts = max(held, key=lambda h: (tail(h[0]), abs(h[1])))
    took, then = tail(seg), "ramped to 0 V, and the next step restarts from its start"
    which = f"the longest upload after step {seg.label.rsplit('/', 1)[-1][:40]} at {volts:.0f} V" + \
        (f"; {len(held)} steps in all" if len(held) > 1 else "")
    hold = (f"~{took:.1f} s at the rate the engine uploads, past the {DRAIN_HOLD_S:g}-s bound: the output held "
            f"{DRAIN_HOLD_S:g} s, then {then}" if took > DRAIN_HOLD_S else
            f"~{took * 1e3:.0f} ms at the rate the engine uploads, more on a busy host; an upload past "
            f"{DRAIN_HOLD_S:g} s has the output {then}")
    return (f"{len(held)} step{'s' if len(held) > 1 else ''} storing laser data end{'' if len(held) > 1 else 's'} "
            f"with the output on ({which}): the last stored values upload after each, the output held at its end "
            f"value meanwhile — {hold}")


def _step_schedule(program: Program, seg: Segment, loads: list[LinkLoad]) -> tuple[float | None, Polls, Polls]:
    """What the engine does in a storing step besides the fetch (:func:`laser_drain_rate`'s ``tick_s``, ``polls``,
    ``after``): the host's time a set-point tick (the amplifier's FC6 where the step sets a voltage and no DAQ plays
    it, the motor's go-to where it sets a position; None: the ticks send nothing), the polls that run before the
    fetch (the instruments' reads, :func:`link_loads`' items) and after it (a DAQ stream's collect, its time unknown
    here: counted as none, its slot still ends a fetch)."""
    amp_daq, _ = _hardware_timed(program)
    sends = [t for link in loads for ch, _, t in link.items
             if (ch.startswith("amplifier set-points") and seg.voltage is not None and not amp_daq)
             or (ch.startswith("motor set-points") and seg.position is not None)]
    polls = tuple((rate, t) for link in loads for ch, rate, t in link.items if "set-points" not in ch and rate > 0)
    after = ((1.0 / COLLECT_PERIOD_S, 0.0),) if amp_daq and seg.duration > 0 else ()
    return (sum(sends) if sends else None), polls, after


def step_drain_rate(program: Program, seg: Segment, setpoint_Hz: float | None = None,
                    loads: list[LinkLoad] | None = None) -> float:
    """Stored values per second the engine uploads while ``seg`` stores, with a backlog (:func:`laser_drain_rate` of
    the step's schedule, :func:`_step_schedule`), at ``setpoint_Hz`` (None: the protocol's); ``loads``: the
    program's :func:`link_loads`, where the caller has them."""
    rig = program.rig
    if rig.laser is None:
        return 0.0
    loads = [link for link in (loads or link_loads(program)) if link.link != "laser"]  # no single reads: it stores
    tick_s, polls, after = _step_schedule(program, seg, loads)
    return laser_drain_rate(rig.laser.baudrate, setpoint_Hz or program.protocol.recording.setpoint_Hz, polls, tick_s,
                            after)


def _check_upload_hold(program: Program, baud: int) -> str | None:
    """One line if, in a step that stores, the laser's storage fills faster than the engine uploads it while the
    step runs (:func:`step_drain_rate`: the engine's fetch poll, each fetch bounded by the step's next action and by
    the driver's per-call budget). A storage that fills faster leaves a backlog that grows over the step, uploaded
    after it (the schedule shifted by that time, the output ramped to 0 V if it is long). Capacity is not this
    check's: a step that stores more than the controller holds is refused by :mod:`bench.protocol.program`
    (``rig.laser.capacity``)."""
    rec = program.protocol.recording
    steps = [s for s in program.segments if s.storing and s.duration > 0]
    if not steps:
        return None
    stored = program.laser_Hz  # as the controller stores it (800 S/s asked: 1000 stored)
    loads = link_loads(program)
    rate, seg = min(((step_drain_rate(program, s, loads=loads), s) for s in steps), key=lambda d: d[0])
    if stored <= rate:
        return None
    fit_Hz = next((f for f in range(math.ceil(rec.setpoint_Hz) - 1, 0, -1)  # set-point rates whose gaps drain it
                   if all(step_drain_rate(program, s, f, loads) >= stored for s in steps)), None)
    fetch_tick = min(FETCH_PERIOD_S, 1.0 / rec.setpoint_Hz)
    least = (LKG_FETCH_OVERHEAD_BYTES + LKG_VALUE_BYTES) * char_time(baud) + 2 * LKG_EXCHANGE_ALLOWANCE_S
    how = (f"one fetch every {fetch_tick * 1e3:.0f} ms, each ending before the step's next set-point or poll and "
           f"after at most {LKG_UPLOAD_CHUNK_S:g} s: the link drains {rate:,.0f} S/s" if rate else
           f"no gap before its next set-point or poll fits a fetch ({least * 1e3:.1f} ms for the status query and "
           "one value): the link drains none in it")
    storable = program.rig.laser.storable_at_most(rate) if program.rig.laser is not None else rate
    slower = f"recording.setpoint_Hz to ≤ {fit_Hz}" if fit_Hz else None
    fit = (f"lower recording.displacement_Hz to ≤ {storable:,.0f}" + (f" or {slower}" if slower else "") if rate else
           f"lower {slower}" if slower else "lower the other channels' rates")
    return (f"laser storage upload: at recording.setpoint_Hz = {rec.setpoint_Hz:g}, {how}; the storage fills "
            f"{stored:,.0f} S/s, the backlog grows over step {seg.label.rsplit('/', 1)[-1][:40]} (uploaded after "
            f"it); {fit}")


def _bounded_fetch(baud: int, within: float) -> tuple[int, float]:
    """(values, seconds) of one ``KeyenceLKG.fetch_buffer(within)`` with a backlog, as the driver sizes it: nothing
    with less than the status query and one value's time; else the ``AN`` status query (3 + 16 characters and one
    exchange allowance), then ``AO`` requests of at most :func:`_upload_chunk` values each sized to end within the
    bound (16 + 3 characters, the allowance, 9 characters a value), until one no longer fits or the call has
    spent its budget (:data:`LKG_UPLOAD_CHUNK_S`: checked before each request after the first)."""
    ct, allowance = char_time(baud), LKG_EXCHANGE_ALLOWANCE_S
    if within < (LKG_FETCH_OVERHEAD_BYTES + LKG_VALUE_BYTES) * ct + 2 * allowance:
        return 0, 0.0
    took, values = (3 + 16) * ct + allowance, 0
    while not (values and took >= LKG_UPLOAD_CHUNK_S):
        left = within - took - (16 + 3) * ct - allowance  # unbounded (no action ahead): a whole request
        n = min(_upload_chunk(baud), max(0, int(left / (LKG_VALUE_BYTES * ct))) if math.isfinite(left) else 1000)
        if n < 1:
            break
        took += (16 + 3 + LKG_VALUE_BYTES * n) * ct + allowance
        values += n
    return values, took


def _cycle(*rates: float) -> float:
    """The span :func:`laser_drain_rate` replays: the schedule's repeat — the least common multiple of the periods
    ``1/rate`` (rates as fractions) — as often as makes a second or more, at most :data:`DRAIN_SPAN_S`."""
    fracs = [Fraction(r).limit_denominator(1000) for r in rates if r > 0]
    den = math.lcm(*(f.denominator for f in fracs))
    repeat = float(1 / Fraction(math.gcd(*(int(f * den) for f in fracs)), den))  # 1 / the rates' common divisor
    return min(DRAIN_SPAN_S, repeat * math.ceil(1.0 / repeat - 1e-9))


@functools.lru_cache(maxsize=1024)  # the check's search over set-point rates asks again for steps alike
def laser_drain_rate(baud: int, setpoint_Hz: float, polls: Polls = (), tick_s: float | None = 0.0,
                     after: Polls = ()) -> float:
    """Stored values per second the engine uploads in a storing step, with a backlog: what the fetches that start in
    one span of its schedule (:func:`_cycle`, after one to settle) upload. It replays :mod:`bench.runtime.engine`'s
    step loop: set-point ticks at ``setpoint_Hz`` (each ``tick_s`` of the host's time; None: the ticks send
    nothing), the ``polls`` (rate, seconds; run before the fetch when due at once) and ``after`` (run after it), and
    the fetch poll every ``min(FETCH_PERIOD_S, 1/setpoint_Hz)`` from one period after the start, each fetch bounded
    by the step's next action — the next tick, another poll's next slot — and uploading what :func:`_bounded_fetch`
    says the driver fits in it. Actions run in time order, none before its slot; a poll whose slots passed while the
    host was busy runs once. The starved fetch's unbounded call (``STARVED_FETCHES`` periods without a value) is not
    counted: it holds the set-points back."""
    period = 1.0 / setpoint_Hz
    least = (LKG_FETCH_OVERHEAD_BYTES + LKG_VALUE_BYTES) * char_time(baud) + 2 * LKG_EXCHANGE_ALLOWANCE_S
    if tick_s is not None and period <= FETCH_PERIOD_S and period - tick_s < least:
        return 0.0  # a fetch every tick, each in less than the tick leaves: none fits (as the replay would find)
    periods = [1.0 / r for r, _ in polls] + [min(FETCH_PERIOD_S, period)] + [1.0 / r for r, _ in after]
    costs = [t for _, t in polls] + [0.0] + [t for _, t in after]
    fetch = len(polls)
    span = _cycle(setpoint_Hz, *(1.0 / p for p in periods))
    count = [0] * len(periods)
    count[fetch] = 1  # nothing is stored at the step's start
    due = [n * p for n, p in zip(count, periods, strict=True)]  # times as the engine computes them: count × period
    k, now, values = 0, 0.0, 0
    while True:
        t_tick = k * period if tick_s is not None else math.inf
        t_next = min(t_tick, *due)
        if t_next >= 2 * span - 1e-12:
            return values / span
        now = max(now, t_next)
        if t_tick <= t_next and tick_s is not None:
            now += tick_s
            k += 1
        for i in [i for i, d in enumerate(due) if d <= t_next + 1e-12]:
            if i != fetch:  # a reading's missed slots are skipped; the fetch's (a backlog) are not
                while (count[i] + 1) * periods[i] <= now:
                    count[i] += 1
                now += costs[i]
            else:
                until = min([k * period if tick_s is not None else math.inf,
                             *(d for j, d in enumerate(due) if j != i and d > t_next + 1e-12)])
                n, took = _bounded_fetch(baud, until - now)
                values += n if span - 1e-12 <= now < 2 * span else 0  # started in the second repeat (on the host's
                now += took  # time: behind its schedule, fewer fetches start in it than are due)
            count[i] += 1
            due[i] = count[i] * periods[i]


def _fit_setpoints(link: LinkLoad) -> str:
    """What would fit on an overloaded link: the set-point rate left by the other traffic."""
    for ch, rate, t in link.items:
        if "set-points" in ch:
            others = link.load - rate * t
            room = (MAX_LOAD * 0.9 - others) / t
            if room > 0:
                return f"lower recording.setpoint_Hz to ≤ {int(room)} (or a faster line / a hardware-timed drive)"
    rates = [f"{ch.split(' (')[0]} ≤ {rate / link.load * 0.9:.0f}/s" for ch, rate, _ in link.items]
    return "lower the polling rates, e.g. " + ", ".join(rates)
