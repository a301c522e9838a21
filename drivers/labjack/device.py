"""The T7 as an instrument: connect (a T7, its calibration, no stream left running, its watchdog), check,
identify, safe state and close, over the pieces in this package."""

from __future__ import annotations

import math

from drivers.errors import InstrumentConnectionError, InstrumentStateError
from drivers.interfaces import CheckResult, Identity
from drivers.labjack.registers import (
    DAC0,
    FIRMWARE_VERSION,
    HARDWARE_VERSION,
    PRODUCT_ID,
    PRODUCT_T7,
    SERIAL_NUMBER,
    STREAM_ENABLE,
    f32_words,
    words_f32,
    words_u32,
)
from drivers.labjack.stream_in import T7Stream
from drivers.labjack.watchdog import T7Watchdog


class LabJackT7(T7Stream, T7Watchdog):
    """Driver of one LabJack T7 over Ethernet (command-response on ``port``, stream on ``stream_port``)."""

    def connect(self) -> None:
        """Open the Modbus link, check it is a T7, read its calibration, stop a stream left running."""
        try:
            self.link.open()
        except InstrumentConnectionError:  # the link's words, naming the device at that address
            raise InstrumentConnectionError(self.name, f"T7 at {self.host}:{self.port}: cannot connect: "
                                            f"{self.link.open_failure}") from None
        product = words_f32(self.read_regs(PRODUCT_ID, 2))  # FC3: a device that is no T7 may not know MBFB
        if not (math.isfinite(product) and round(product) == PRODUCT_T7):  # inf, NaN, negative: one line too
            raise InstrumentStateError(self.name, f"PRODUCT_ID (register {PRODUCT_ID}) reads {product:g}, "
                                       f"expected {PRODUCT_T7} (T7)")
        serial, running = self.feedback([(SERIAL_NUMBER, 2), (STREAM_ENABLE, 2)])  # one MBFB packet
        self.serial = words_u32(serial)
        self.cal = self.read_calibration()
        if words_u32(running):
            self.write_u32(STREAM_ENABLE, 0)
        if self.watchdog_s is not None:
            self.configure_watchdog(self.watchdog_s, self.safe_dac)

    def check(self) -> CheckResult:
        """Whether a stream runs; AIN0 by command-response."""
        return CheckResult("stream running" if self.streaming else "idle", (("AIN0", self.read_ain(0)),))

    def identify(self) -> Identity:
        """PRODUCT_ID, serial number, firmware and hardware versions."""
        serial, firmware, hardware = self.feedback([(SERIAL_NUMBER, 2), (FIRMWARE_VERSION, 2),
                                                    (HARDWARE_VERSION, 2)])  # one MBFB packet
        return Identity("LabJack", "T7", {"serial": str(words_u32(serial)), "firmware": f"{words_f32(firmware):.4f}",
                                          "hardware": f"{words_f32(hardware):.2f}"})

    def safe_state(self) -> None:
        """Stop the stream (the DACs stop updating) and write the safe DAC values, both DACs in one MBFB packet (one
        failing cannot leave the other unwritten) — all of it goes out even after a stop request has cancelled the
        rig's waits."""
        if not self.link.is_open:
            return
        try:
            self.stop(always_send=True)
        finally:
            self.feedback([(DAC0 + 2 * ch, f32_words(self.dac_output(ch, v)[0])) for ch, v in enumerate(self.safe_dac)],
                          always_send=True)

    def close(self) -> None:
        """Safe state, then release both sockets."""
        try:
            self.safe_state()
        finally:
            self._close_stream_socket()
            self.link.close()
