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
following ticks), single reads at ``PASSIVE_LASER_HZ`` otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from bench.protocol.program import HOLD_KEEPALIVE_S, PASSIVE_LASER_HZ, Program

TURNAROUND_MODBUS_S = 1e-3  # ADAM / DGT1S request → reply [assumed: no figure in the manuals read]
TURNAROUND_LKG_S = 0.5e-3  # LK-G command → reply [assumed]
TURNAROUND_LINRS_S = 1e-3  # LinMot telegram → response [assumed]
ADAM_4017P_RATE = 10.0  # conversions/s over all enabled channels (datasheet)
DGT1S_RATE = 100.0  # conversions/s [assumed: the DGT1S offers several rates]
LKG_VALUE_BYTES = 9  # one stored value in an AO reply: 8 characters and a comma (manual p. 5-6)
LKG_UPLOAD_CHUNK_S = 0.2  # the driver sizes AO requests to this much wire time
LKG_EXCHANGE_ALLOWANCE_S = 2e-3  # the driver's allowance per exchange beyond its characters (a bounded fetch's)
MAX_LOAD = 1.0  # a link busy more than this fraction of the time cannot keep up


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


def _check_upload_hold(program: Program, baud: int) -> str | None:
    """One line if, in a step that both stores and streams set-points, the laser's storage fills faster than the
    link can drain it in the time the set-points leave.

    What a fetch no longer limits: the engine bounds each upload in rig time by the step's next action (a set-point,
    another poll; ``bench.runtime.polls``) and leaves what it could not upload for the following ticks, so a fetch
    holds no set-point back however much was stored (before, one 0.25-s fetch of 125 values at 500 S/s held the host
    ~102 ms and set-points were skipped). What is left is throughput. In each set-point period ``T = 1/setpoint_Hz``
    the host first sends the tick's set-points and the polls due — on average ``U·T``, ``U`` the share of the time
    the other channels keep it on their wires (:func:`link_loads`) — and the upload has the rest, ``T − U·T``. One
    fetch at most runs in it (the poll comes once a tick), paying its fixed exchange — the ``AN`` status query and
    the ``AO`` request and its reply's head, 38 characters, and the driver's allowance of
    :data:`LKG_EXCHANGE_ALLOWANCE_S` per exchange (the driver sizes its request by it) — and 9 characters a value
    (manual p. 5-6). So a tick drains at most ``n = ⌊(T − U·T − 38·c − 2·a) / (9·c)⌋`` values (``c`` = 10/baud s a
    character), ``n·setpoint_Hz`` values/s: a storage that fills faster leaves a backlog that grows over the step,
    uploaded after it (the schedule shifted by that time, the output ramped to 0 V if it is long). Counted as if
    the link were always behind (a fetch every tick): caught up, the engine fetches every ``FETCH_PERIOD_S`` only.
    Capacity is not this check's: a step that stores more than the controller holds is refused by
    :mod:`bench.protocol.program` (``rig.laser.capacity``)."""
    rec = program.protocol.recording
    amp_daq, _ = _hardware_timed(program)  # a DAQ plays the voltage itself: only go-tos are the host's to send
    steps = [s for s in program.segments if s.storing and s.stream_until > s.t_start
             and ((s.voltage is not None and not amp_daq) or s.position is not None)]
    if not steps:
        return None
    loads = [link for link in link_loads(program) if link.link != "laser"]  # no single reads while it stores
    others = sum(link.load for link in loads)
    setpoints = sum(rate * t for link in loads for ch, rate, t in link.items if "set-points" in ch)
    drain = laser_drain_rate(baud, rec.setpoint_Hz, others)
    stored = program.laser_Hz  # as the controller stores it (800 S/s asked: 1000 stored)
    if stored <= drain:
        return None
    period = 1.0 / rec.setpoint_Hz
    fits = [f for f in range(int(rec.setpoint_Hz) - 1, 0, -1)  # set-point rates whose gaps drain the storage
            if laser_drain_rate(baud, f, others - setpoints * (1 - f / rec.setpoint_Hz)) >= stored]
    n = int(drain / rec.setpoint_Hz)
    fixed = (16 + 3 + 3 + 16) * char_time(baud) + 2 * LKG_EXCHANGE_ALLOWANCE_S
    drains = (f"one fetch of ≤ {n} values: the link drains {drain:,.0f} S/s" if n else
              f"too little for a fetch ({fixed * 1e3:.1f} ms before its first value): the link drains none in it")
    storable = program.rig.laser.storable_at_most(drain) if program.rig.laser is not None else drain
    fit = (f"lower recording.displacement_Hz to ≤ {storable:,.0f}" + (f" or recording.setpoint_Hz to ≤ {fits[0]}"
                                                                    if fits else "") if n else
           f"lower recording.setpoint_Hz to ≤ {fits[0]}" if fits else "lower the other channels' rates")
    return (f"laser storage upload: at recording.setpoint_Hz = {rec.setpoint_Hz:g} each {period * 1e3:.0f}-ms "
            f"period leaves ~{(1 - others) * period * 1e3:.0f} ms after its set-points and polls, {drains}; the "
            f"storage fills {stored:,.0f} S/s, the backlog grows over step "
            f"{steps[0].label.rsplit('/', 1)[-1][:40]} (uploaded after it); {fit}")


def laser_drain_rate(baud: int, setpoint_Hz: float, others: float) -> float:
    """Stored values per second the engine uploads in a step that streams ``setpoint_Hz`` set-points while the other
    channels keep the host ``others`` of the time: one fetch a set-point period in what the tick leaves (see
    :func:`_check_upload_hold`)."""
    ct = char_time(baud)
    period = 1.0 / setpoint_Hz
    window = period * (1 - others) - (16 + 3 + 3 + 16) * ct - 2 * LKG_EXCHANGE_ALLOWANCE_S
    return max(0, math.floor(window / (LKG_VALUE_BYTES * ct))) * setpoint_Hz


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
