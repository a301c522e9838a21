"""LabJack T7 multifunction DAQ: Modbus TCP command-response and hardware-timed stream (in and out).

Sources: LabJack T-Series Datasheet §3.2 (stream mode, §3.2.1/3.2.3 stream-out, §3.2.2/3.2.4 low-level
streaming), the register map (``ljm_constants.json`` in labjack/ljm_constants, which the datasheet's
register tables are generated from) and LabJack's own low-level TCP stream example
(``t7_modbus_tcp_stream_example.c`` with ``stream.c``/``calibration.c``). Every number below is marked:

Datasheet [D] = T-Series Datasheet §3.2 and its register map (ljm_constants.json); example [E] = LabJack's
low-level TCP stream example; [A] = assumed, to check on a real T7.

* [E] ports: command-response TCP 502, spontaneous stream TCP 702; Modbus unit id 1.
* [D] big-endian bytes, 32-bit values high word first.
* [D] AIN#(0:249) 0+2n F32 R; DAC#(0:1) 1000+2n F32 RW; AIN#_RANGE 40000+2n F32 (10/1/0.1/0.01);
  AIN#_NEGATIVE_CH 41000+n U16 (199 = single-ended); LAST_ERR_DETAIL 55000 U16; PRODUCT_ID 60000 F32 (7);
  HARDWARE_VERSION 60002 F32; FIRMWARE_VERSION 60004 F32; SERIAL_NUMBER 60028 U32.
* [D] watchdog: WATCHDOG_ENABLE_DEFAULT 61600 U32, _TIMEOUT_S_DEFAULT 61604 U32 (whole seconds),
  _DAC0_ENABLE_DEFAULT 61640 U32, _DAC0_DEFAULT 61642 F32, _DAC1_ENABLE_DEFAULT 61650, _DAC1_DEFAULT 61652;
  "must be disabled before writing any of the other watchdog registers"; any communication clears the timer.
  [A] the _DEFAULT registers live in flash: the driver reads them and writes only what differs.
* [D] STREAM_SCANRATE_HZ 4002 F32, _NUM_ADDRESSES 4004, _SAMPLES_PER_PACKET 4006, _SETTLING_US 4008 F32,
  _RESOLUTION_INDEX 4010, _BUFFER_SIZE_BYTES 4012 (power of 2, T7 ≤ 32768), _CLOCK_SOURCE 4014,
  _AUTO_TARGET 4016 (bit 0: packets to port 702), STREAM_DATATYPE 4018 = 0, _NUM_SCANS 4020 (0: continuous),
  STREAM_SCANLIST_ADDRESS#(0:127) 4100+2i, STREAM_ENABLE 4990 written last.
* [D] stream-out: STREAM_OUT#(0:3) 4800+n in the scan list (returns no data); _TARGET 4040+2n,
  _BUFFER_ALLOCATE_NUM_BYTES 4050+2n (power of 2, 32…16384; usable = bytes/2 − 1 values), _LOOP_NUM_VALUES
  4060+2n, _SET_LOOP 4070+2n (1 = use new data now), _BUFFER_STATUS 4080+2n, _ENABLE 4090+2n,
  _BUFFER_U16 4420+n; order: target, allocate, enable, loop size, data, set-loop; after the data the last
  LOOP_NUM_VALUES values repeat (1: the output holds the end value exactly). The driver keeps at most
  ``StreamSpec.out_ahead_s`` of values in the device ahead of the scan its scan clock may have reached (t0 + k/rate
  on the host clock, t0 known to the enable request's round trip; a lost host then stops the drive within it),
  topping up in chunks of at most a packet and at least a quarter of that; the device past the values written
  (the scan clock's lower bound) is an underrun (``out_underrun_scans``).
* [D] looping (register map: LOOP_NUM_VALUES, SET_LOOP "1 = use new data immediately"; LabJack's stream-out update
  example: a loop "will not be interrupted until [it] is complete", then the next data plays): with
  ``StreamSpec.out_ahead_s`` and ``out_loops``, a stretch of whole periods whose codes repeat exactly
  (:mod:`.looping`) is written once as a block of at least ``out_ahead_s`` and played from the device's loop; in its
  last repetitions, when the scan clock's bounds place the device surely within one repetition (a packet's margin
  included), the values after it are written with SET_LOOP. A device past the last repetition is an underrun.
* [A] a buffer register takes k values in one Modbus Feedback write frame of k registers at its address
  ([D] register map: STREAM_OUT#_BUFFER_U16 is a buffer register, "a sequence of values to a single address").
* [D] Modbus Feedback (MBFB), function 76: after the function code, frames of type (1 byte: 0 read, 1 write),
  address (2), number of registers (1), then for a write 2·n data bytes; the reply carries the function code
  and the read frames' data in order. [D] T7 Ethernet packets ≤ 1040 bytes (LabJackM.h,
  LJM_MAX_ETHERNET_PACKET_NUM_BYTES_T7). [A] an error is answered as a Modbus exception (function 0xCC and a
  code, anything after it ignored); the stream-out buffer is topped up through MBFB (510 values a packet, not
  120 — four times fewer exchanges per second of waveform). Command-response work that can share a packet does
  (:meth:`~LabJackT7.feedback`: reads and writes in order, one round trip): connect's serial, stream state and
  calibration, the watchdog's settings, arm's registers with the scan rate read back, DAC reads and writes;
  PRODUCT_ID (the first request, to a device that may be no T7), single AIN reads and the stream's stop are FC3/FC16.
* [E] packet: TransID(2) ProtoID(2)=0 Length(2) Unit(1)=1 Function(1)=76 Type(1)=16 Reserved(1)
  Backlog(2, bytes) Status(2) AddInfo(2), then samples (2 bytes, MSB first, scan-list order, STREAM_OUT
  entries excluded); TransID 0 at STREAM_ENABLE, +1 per packet. [A] Length = 10 + 2·samples (MBAP rule).
* [D][E] status 2940 auto-recover active, 2941 end (AddInfo = scans skipped; one dummy scan of 0xFFFF first
  [E, U3 manual]), 2942 scan overlap, 2943 skip-counter overflow, 2944 burst complete, 2945 buffer full.
* [A] a burst's last packet may be shorter than STREAM_SAMPLES_PER_PACKET; a stop discards a partial packet.
* [D] first scan one scan period after STREAM_ENABLE = 1 (STREAM_START_TIME_STAMP); scan rate > 152.588 Hz
  is 10 MHz / round(10 MHz / rate), read back from 4002.
* [E] calibration: flash pointer 61810 ← 0x3C4000 + 52·i, reads of 61812 of 26, 26, 26, 4 registers = 41
  F32 (HS[4], HR[4] × PSlope/NSlope/Center/Offset, DAC[2] × Slope/Offset, temperature, current sources,
  I_bias); raw → V = (raw − Center)·PSlope if raw ≥ Center else (Center − raw)·NSlope, gain 0..3 = ±10/1/0.1/
  0.01 V. [A] DAC code = V·Slope + Offset; [D] the 12-bit DAC ignores the low 4 bits of DAC#_BINARY.
* [D] error names (LAST_ERR_DETAIL); [A] which Modbus exception code carries them (the driver reads 55000–55002,
  LAST_ERR_DETAIL, LAST_MB_ERR, LAST_ERR_FRAME, in one FC3 request after any exception).
* [D] LAST_ERR_FRAME 55002 U16 R: "the frame number that caused the last error". [A] MBFB frames are numbered from
  1 in the packet as sent: the register's default is 0, as LAST_ERR_DETAIL's 0 is "no error", and numbering from 1
  keeps 0 free for "no frame". An MBFB refusal names that frame (its number, read/write, address and registers);
  a number outside the packet, or error registers that cannot be read, list the packet's frames instead (and the
  number): were the count from 0, the message would name the frame after the failing one, its number shown to check.

Why spontaneous stream on its own socket rather than command-response stream (STREAM_DATA_CR 4500): the
datasheet documents the spontaneous packet byte by byte (and LabJack's example parses it); the C-R read
format is not given in the material we have. The Modbus client (pymodbus via :class:`ModbusLink`) carries
configuration and stream-out buffer updates; a plain TCP socket carries the packets.

Engine API (bluesky-style): :meth:`LabJackT7.arm` (stage: configure inputs, scan list, preload stream-out),
:meth:`~LabJackT7.kickoff` (STREAM_ENABLE = 1; returns the rig time of scan 0), :meth:`~LabJackT7.collect`
(complete scans received so far, numbered, refilling the stream-out buffer), :meth:`~LabJackT7.complete`
(wait until the burst or the waveform is done), :meth:`~LabJackT7.stop`.

The driver in pieces by responsibility (one class, :class:`LabJackT7`, composed of them): :mod:`.registers` (the
register map and Modbus encodings), :mod:`.calibration`, :mod:`.packets` (the stream packet), :mod:`.plan` (an
armed stream's plan and state), :mod:`.connection` (command-response: register I/O, calibration read, single
inputs), :mod:`.watchdog`, :mod:`.stream_out` (DAC values and the stream-out; :mod:`.looping`, where it repeats),
:mod:`.stream_in` (arm, kickoff,
collect, complete, stop), :mod:`.device` (connect, check, identify, safe state, close). Import from here.
"""

from drivers.interfaces import StreamBlock, StreamIn, StreamOut, StreamSpec  # the stream's types: the DAQ contract's
from drivers.labjack.calibration import Calibration
from drivers.labjack.device import LabJackT7
from drivers.labjack.packets import StreamPacket, parse_stream_packet
from drivers.labjack.plan import StreamPlan
from drivers.labjack.registers import (
    CR_PORT,
    DAC_RANGE,
    MBFB_MAX_BYTES,
    OUT_PACKET_VALUES,
    STREAM_PORT,
    UNIT,
    Feedback,
    feedback_packets,
)

__all__ = ["CR_PORT", "DAC_RANGE", "MBFB_MAX_BYTES", "OUT_PACKET_VALUES", "STREAM_PORT", "UNIT", "Calibration",
           "Feedback", "LabJackT7", "StreamBlock", "StreamIn", "StreamOut", "StreamPacket", "StreamPlan", "StreamSpec",
           "feedback_packets", "parse_stream_packet"]
