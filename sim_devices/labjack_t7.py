"""Simulated LabJack T7 (the twin lives in :mod:`sim_devices.t7`; this module keeps the names other code imports)."""

from sim_devices.t7.analog import Conditioning, Signal, default_signals, nominal_calibration
from sim_devices.t7.device import LabJackT7Sim
from sim_devices.t7.feedback import FeedbackPDU
from sim_devices.t7.registers import (
                                      MODBUS_PORT,
                                      N_AIN,
                                      R_AIN,
                                      R_AIN_NEG,
                                      R_AIN_RANGE,
                                      R_DAC,
                                      R_ENABLE,
                                      R_LAST_ERR,
                                      R_O_F32,
                                      R_O_U16,
                                      REGISTERS,
                                      STREAM_PORT,
                                      UNIT,
)
from sim_devices.t7.stream_out import OutChannel

__all__ = [
                                      "MODBUS_PORT",
                                      "N_AIN",
                                      "REGISTERS",
                                      "R_AIN",
                                      "R_AIN_NEG",
                                      "R_AIN_RANGE",
                                      "R_DAC",
                                      "R_ENABLE",
                                      "R_LAST_ERR",
                                      "R_O_F32",
                                      "R_O_U16",
                                      "STREAM_PORT",
                                      "UNIT",
                                      "Conditioning",
                                      "FeedbackPDU",
                                      "LabJackT7Sim",
                                      "OutChannel",
                                      "Signal",
                                      "default_signals",
                                      "nominal_calibration",
]
