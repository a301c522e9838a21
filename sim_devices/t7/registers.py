"""The T7's Modbus register map as the twin serves it: addresses, types and access, error codes.

Written from LabJack's published register map (``ljm_constants.json``, the source of the Modbus Map pages of the
T-Series Datasheet; a copy of the part the twin serves is ``tests/data/ljm_constants_t7.json``, which a test compares
with :data:`REGISTERS` address by address) and the datasheet, independently of :mod:`drivers.labjack`.
Big-endian, high word first ([D] datasheet §3.1 Modbus).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Literal

# ---- the map's numbers, written out here (never imported from the driver) ----
R_AIN, R_DAC, R_AIN_RANGE, R_AIN_NEG, R_AIN_ALL_RANGE = 0, 1000, 40000, 41000, 43900
R_AIN_RES, R_AIN_ALL_RES = 41500, 43903  # AIN#_RESOLUTION_INDEX, AIN_ALL_RESOLUTION_INDEX (UINT16)
N_AIN = 14  # wired, externally connected inputs AIN0–AIN13
N_AIN_ALL = 16  # [D] AIN14: internal temperature sensor, AIN15: internal ground (T7 datasheet §14.0 AIN)
R_DIO, R_FIO_STATE, R_FIO_DIR, R_DIO_STATE, R_DIO_DIR = 2000, 2500, 2600, 2800, 2850
N_DIO = 23  # [D] FIO0–7, EIO0–7, CIO0–3, MIO0–2 (DIO0–22)
DIO_PORTS = ((0, 8), (8, 8), (16, 4), (20, 3))  # FIO, EIO, CIO, MIO: (first DIO, lines)
R_RATE, R_NADDR, R_SPP, R_SETTLE, R_RES, R_BUFSIZE, R_CLKSRC, R_TARGET, R_DTYPE, R_NSCANS, R_EXTDIV = (
    4002, 4004, 4006, 4008, 4010, 4012, 4014, 4016, 4018, 4020, 4022)
R_RATE_ACTUAL = 4494
R_SCANLIST, R_ENABLE = 4100, 4990
R_O_TARGET, R_O_ALLOC, R_O_LOOP, R_O_SETLOOP, R_O_STATUS, R_O_ENABLE = 4040, 4050, 4060, 4070, 4080, 4090
R_O_F32, R_O_U16, R_O_SCAN = 4400, 4420, 4800
R_LAST_ERR, R_LAST_MB_ERR, R_LAST_ERR_FRAME = 55000, 55001, 55002  # LAST_ERR_DETAIL, LAST_MB_ERR, LAST_ERR_FRAME
R_TEST, R_TEST_U16, R_TEST_U32, R_TEST_I32, R_TEST_F32 = 55100, 55110, 55120, 55122, 55124
R_PRODUCT, R_HW, R_FW, R_BOOT, R_SERIAL = 60000, 60002, 60004, 60006, 60028
R_CORE_TIMER = 61520
R_FLASH_PTR, R_FLASH_READ, FLASH_CAL = 61810, 61812, 0x3C4000
# [D] watchdog (WATCHDOG_*_DEFAULT): ENABLE 61600 U32, TIMEOUT_S 61604 U32, DAC0_ENABLE 61640 U32, DAC0 61642 F32,
# DAC1_ENABLE 61650 U32, DAC1 61652 F32; "the watchdog must be disabled before writing any of the other watchdog
# registers"
R_WD_ENABLE, R_WD_TIMEOUT, R_WD_DAC_EN, R_WD_DAC = 61600, 61604, (61640, 61650), (61642, 61652)

# ---- values the map states ----
TEST_VALUE = 0x00112233  # [D] TEST: "should always return 0x00112233"; also TEST_UINT32's default
TEST_DEFAULTS = {R_TEST_U16: 0x0011, R_TEST_U32: 0x00112233, R_TEST_I32: -2003195205, R_TEST_F32: -9999.0}
AIN_ALL_MIXED = -9999.0  # [D] AIN_ALL_RANGE read when the inputs' ranges differ
CORE_CLOCK_HZ = 80e6  # [D] "a core clock of 80 MHz" (STREAM_SCANRATE_HZ); CORE_TIMER runs at half of it

# ---- error codes (LAST_ERR_DETAIL) ----
E_ILLEGAL_ADDRESS = 1202  # [D] ljm_constants.json errors: LJME_MBE2_ILLEGAL_DATA_ADDRESS, "an invalid address …
# or illegal access to a device register such as trying to write to a read only register"
E_RSP_OVERFLOW = 2300  # [D] ljm_constants.json errors: MODBUS_RSP_OVERFLOW, "Response packet greater than max
# packet size."
E_AIN_RANGE, E_AIN_RESOLUTION = 2370, 2375  # [D] AIN_RANGE_INVALID ("Specified range not available on this
# device"), AIN_RESOLUTION_INVALID ("Selected resolution is invalid")
E_WD_ENABLED = 2671  # [D] SWDT_ENABLED: "The watchdog must be disabled before the requested operation …"
E_RES_INDEX, E_SETTLING, E_TEMP_RATE = 2606, 2621, 2631  # [D] STREAM_CONFIG_INVALID ("Stream resolution can not be
# greater than 8"), STREAM_SETTLING_INVALID, STREAM_RATE_INVALID_FOR_TEMPERATURE_SENSOR ("… above 250Hz")
MAX_STREAM_RES_INDEX, MAX_SETTLING_US, MAX_TEMP_SCAN_HZ = 8, 4400.0, 250.0  # [D] STREAM_RESOLUTION_INDEX "Valid
# values: 0-8"; STREAM_SETTLING_US "Max is 4400"; the temperature sensor's 250 Hz (error 2631)
E_ACTIVE, E_CHN_LIST, E_RATE, E_DTYPE, E_TARGET, E_OUT_FULL, E_BUFSIZE, E_OUT_DNE, E_SPP, E_NOT_RUNNING, \
    E_LOOP_BIG, E_OUT_DISABLED, E_NO_CHN, E_OUT_TARGET = (
        2605, 2607, 2608, 2611, 2612, 2613, 2615, 2617, 2618, 2620, 2622, 2627, 2600, 2614)
S_RECOVER, S_RECOVER_END, S_BURST = 2940, 2941, 2944
S_RECOVER_OVERFLOW = 2943  # [D] ljm_constants.json errors: STREAM_AUTO_RECOVER_END_OVERFLOW, "During stream
# auto-recovery, the variable tracking the number of skipped scans has reached an overflow condition."
SKIPPED_MAX = 0xFFFF  # [E] the skipped-scan counter is 16 bits (AddInfo of the 2941 packet; the example: "the skipped
# samples counter (16-bit) overflowed")
UNIT = 1  # [E] the unit id of the device's Modbus replies and stream packets
FC_FEEDBACK, FEEDBACK_MAX_PACKET = 76, 1040  # [D] MBFB; T7 Ethernet packet bytes (MBAP header included)
MODBUS_PORT, STREAM_PORT = 502, 702  # [D] the T7's Modbus TCP port and its spontaneous-stream port (STREAM_AUTO_TARGET
# bit 0: "Send to Ethernet 702 sockets")

Kind = Literal["UINT16", "UINT32", "INT32", "FLOAT32"]
F32: Kind = "FLOAT32"
U32: Kind = "UINT32"
I32: Kind = "INT32"
U16: Kind = "UINT16"
Access = Literal["R", "W", "RW"]


@dataclass(frozen=True)
class Register:
    """One register of the map: its name (as the map expands ``NAME#(0:3)``), start address, type and access."""

    name: str
    address: int
    kind: Kind
    access: Access

    @property
    def words(self) -> int:
        """Modbus registers it spans."""
        return 1 if self.kind == U16 else 2


def _family(name: str, base: int, n: int, kind: Kind, access: Access, first: int = 0) -> list[Register]:
    """``NAME#(first:first+n-1)``: ``#`` replaced by the index, addresses ``base`` + its offset × register size."""
    size = 1 if kind == U16 else 2
    return [Register(name.replace("#", str(first + i)), base + size * i, kind, access) for i in range(n)]


def _table() -> dict[int, Register]:
    regs = [
        *_family("AIN#", R_AIN, N_AIN_ALL, F32, "R"),
        *_family("DAC#", R_DAC, 2, F32, "RW"),
        *_family("FIO#", R_DIO, 8, U16, "RW"), *_family("EIO#", R_DIO + 8, 8, U16, "RW"),
        *_family("CIO#", R_DIO + 16, 4, U16, "RW"), *_family("MIO#", R_DIO + 20, 3, U16, "RW"),
        *[Register(f"{p}_STATE", R_FIO_STATE + i, U16, "RW") for i, p in enumerate(("FIO", "EIO", "CIO", "MIO"))],
        *[Register(f"{p}_DIRECTION", R_FIO_DIR + i, U16, "RW") for i, p in enumerate(("FIO", "EIO", "CIO", "MIO"))],
        Register("DIO_STATE", R_DIO_STATE, U32, "RW"), Register("DIO_DIRECTION", R_DIO_DIR, U32, "RW"),
        Register("STREAM_SCANRATE_HZ", R_RATE, F32, "RW"), Register("STREAM_NUM_ADDRESSES", R_NADDR, U32, "RW"),
        Register("STREAM_SAMPLES_PER_PACKET", R_SPP, U32, "RW"), Register("STREAM_SETTLING_US", R_SETTLE, F32, "RW"),
        Register("STREAM_RESOLUTION_INDEX", R_RES, U32, "RW"),
        Register("STREAM_BUFFER_SIZE_BYTES", R_BUFSIZE, U32, "RW"),
        Register("STREAM_CLOCK_SOURCE", R_CLKSRC, U32, "RW"), Register("STREAM_AUTO_TARGET", R_TARGET, U32, "RW"),
        Register("STREAM_DATATYPE", R_DTYPE, U32, "RW"), Register("STREAM_NUM_SCANS", R_NSCANS, U32, "RW"),
        Register("STREAM_EXTERNAL_CLOCK_DIVISOR", R_EXTDIV, U32, "RW"),
        Register("STREAM_SCANRATE_HZ_ACTUAL", R_RATE_ACTUAL, F32, "R"),
        *_family("STREAM_SCANLIST_ADDRESS#", R_SCANLIST, 128, U32, "RW"),
        Register("STREAM_ENABLE", R_ENABLE, U32, "RW"),
        *_family("STREAM_OUT#_TARGET", R_O_TARGET, 4, U32, "RW"),
        *_family("STREAM_OUT#_BUFFER_ALLOCATE_NUM_BYTES", R_O_ALLOC, 4, U32, "RW"),
        *_family("STREAM_OUT#_LOOP_NUM_VALUES", R_O_LOOP, 4, U32, "RW"),
        *_family("STREAM_OUT#_SET_LOOP", R_O_SETLOOP, 4, U32, "W"),
        *_family("STREAM_OUT#_BUFFER_STATUS", R_O_STATUS, 4, U32, "R"),
        *_family("STREAM_OUT#_ENABLE", R_O_ENABLE, 4, U32, "RW"),
        *_family("STREAM_OUT#_BUFFER_F32", R_O_F32, 4, F32, "W"),
        *_family("STREAM_OUT#_BUFFER_U16", R_O_U16, 4, U16, "W"),
        *_family("STREAM_OUT#", R_O_SCAN, 4, U16, "R"),
        *_family("AIN#_RANGE", R_AIN_RANGE, N_AIN_ALL, F32, "RW"),
        *_family("AIN#_NEGATIVE_CH", R_AIN_NEG, N_AIN_ALL, U16, "RW"),
        Register("AIN_ALL_RANGE", R_AIN_ALL_RANGE, F32, "RW"),
        *_family("AIN#_RESOLUTION_INDEX", R_AIN_RES, N_AIN_ALL, U16, "RW"),
        Register("AIN_ALL_RESOLUTION_INDEX", R_AIN_ALL_RES, U16, "RW"),
        Register("LAST_ERR_DETAIL", R_LAST_ERR, U16, "R"), Register("LAST_MB_ERR", R_LAST_MB_ERR, U16, "R"),
        Register("LAST_ERR_FRAME", R_LAST_ERR_FRAME, U16, "R"),
        Register("TEST", R_TEST, U32, "R"), Register("TEST_UINT16", R_TEST_U16, U16, "RW"),
        Register("TEST_UINT32", R_TEST_U32, U32, "RW"), Register("TEST_INT32", R_TEST_I32, I32, "RW"),
        Register("TEST_FLOAT32", R_TEST_F32, F32, "RW"),
        Register("PRODUCT_ID", R_PRODUCT, F32, "R"), Register("HARDWARE_VERSION", R_HW, F32, "R"),
        Register("FIRMWARE_VERSION", R_FW, F32, "R"), Register("BOOTLOADER_VERSION", R_BOOT, F32, "R"),
        Register("SERIAL_NUMBER", R_SERIAL, U32, "R"),
        Register("CORE_TIMER", R_CORE_TIMER, U32, "R"),
        Register("WATCHDOG_ENABLE_DEFAULT", R_WD_ENABLE, U32, "RW"),
        Register("WATCHDOG_TIMEOUT_S_DEFAULT", R_WD_TIMEOUT, U32, "RW"),
        *[Register(f"WATCHDOG_DAC{k}_ENABLE_DEFAULT", R_WD_DAC_EN[k], U32, "RW") for k in (0, 1)],
        *[Register(f"WATCHDOG_DAC{k}_DEFAULT", R_WD_DAC[k], F32, "RW") for k in (0, 1)],
        Register("INTERNAL_FLASH_READ_POINTER", R_FLASH_PTR, U32, "RW"),
        Register("INTERNAL_FLASH_READ", R_FLASH_READ, U32, "R"),
    ]
    return {r.address: r for r in regs}


REGISTERS: dict[int, Register] = _table()
"""Every register the twin serves, by start address."""

NOT_IN_MAP = {R_DTYPE: "STREAM_DATATYPE: written (0) by LabJack's low-level stream example [E]; the current "
                       "ljm_constants.json no longer lists it"}
"""Served registers the published map lacks, and why the twin serves them."""


def words(kind: Kind, value: float) -> list[int]:
    """The register words of ``value`` as ``kind`` (big-endian, high word first)."""
    if kind == F32:
        return list(struct.unpack(">HH", struct.pack(">f", value)))
    if kind in (U32, I32):
        v = int(value) & 0xFFFFFFFF
        return [v >> 16, v & 0xFFFF]
    return [int(value) & 0xFFFF]


def value_of(kind: Kind, w: list[int]) -> float:
    """The value that the register words ``w`` (as many as ``kind`` spans) carry."""
    if kind == F32:
        return float(struct.unpack(">f", struct.pack(">HH", *w))[0])
    if kind == U16:
        return w[0]
    v = w[0] << 16 | w[1]
    return v - (1 << 32) if kind == I32 and v & 0x80000000 else v
