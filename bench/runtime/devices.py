"""Checking a rig's instruments, and writing a rig file that points at running simulated twins."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from bench.rig import RigConfig, rig_to_toml
from bench.runtime.instruments import build_instruments
from bench.runtime.rig_lock import claimed
from bench.units import si
from drivers.errors import InstrumentError
from drivers.interfaces import Reading

CLOSE = "close"  # the role of a row that is no instrument: an error met while closing them all


@dataclass(frozen=True)
class CheckRow:
    """Outcome of checking one instrument (``role`` :data:`CLOSE`: of closing the instruments)."""

    role: str
    ok: bool
    identity: str = ""
    state: str = ""
    reading: str = ""
    error: str = ""

    @property
    def instrument(self) -> bool:
        """Whether the row is an instrument's (not an error met while closing them)."""
        return self.role != CLOSE


def _reading(quantity: str, r: Reading) -> str:
    """``quantity value unit`` with an SI prefix (the driver's unit), or why it is not a measurement."""
    return f"{quantity} {si(r.value, r.unit)}" if r.ok else f"{quantity} {r.status}"


def check_instruments(rig: RigConfig, endpoints: dict[str, str] | None = None) -> list[CheckRow]:
    """Connect to every instrument, identify it, read it once, leave it safe; one row per instrument, then one
    (role :data:`CLOSE`) per error met while closing them. Refused
    (RigInUseError, nothing touched) while another process drives one of them: a check would disturb its run."""
    with claimed(rig, endpoints):
        return _check_claimed(rig, endpoints)


def _check_claimed(rig: RigConfig, endpoints: dict[str, str] | None) -> list[CheckRow]:
    inst = build_instruments(rig, endpoints)
    rows: list[CheckRow] = []
    try:
        for role, drv in inst.items():
            try:
                drv.connect()
                ident = str(drv.identify())
                found = drv.check()
                rows.append(CheckRow(role, True, ident, found.state,
                                     ", ".join(_reading(q, r) for q, r in found.readings)))
            except InstrumentError as exc:
                rows.append(CheckRow(role, False, error=str(exc)))
    finally:
        for err in inst.close():
            rows.append(CheckRow(CLOSE, False, error=err))
    return rows


def failures(rows: list[CheckRow]) -> str:
    """The check's failures in one line ('' when none): the instruments that failed, counted among the rig's
    instruments (a row of closing them is none), then what closing them met."""
    checked = [r for r in rows if r.instrument]
    failed = [r for r in checked if not r.ok]
    closing = [r.error for r in rows if not r.instrument]
    said = []
    if failed:
        said.append(f"{len(failed)} of {len(checked)} instruments failed: " + "; ".join(r.error for r in failed))
    if closing:
        said.append("closing the instruments: " + "; ".join(closing))
    return "; ".join(said)


def served_rig(rig: RigConfig, ports: dict[str, str], wire_time: bool = True) -> RigConfig:
    """The rig as seen from outside: real (not simulated), ports set to the running twins' endpoints (the DAQ's
    ``host:port:stream_port`` endpoint sets ``daq.host``, ``daq.port`` and ``daq.stream_port``); ``wire_time``:
    whether the twins take their lines' wire time (false: readings' stamps take none off)."""
    data = rig.model_dump()
    data["simulated"] = False
    data["simulation"]["wire_time"] = wire_time
    data["name"] = f"{rig.name}-served"
    for name, port in ports.items():
        if name == "daq" and data.get("daq") is not None:  # the T7 twin: "host:port:stream_port" (two sockets)
            host, modbus, stream = port.rsplit(":", 2)
            data["daq"].update(host=host, port=int(modbus), stream_port=int(stream))
        elif name in data.get("buses", {}):
            data["buses"][name]["port"] = port
        elif data.get(name) is not None:
            data[name]["port"] = port
    return RigConfig.model_validate(data)


def write_rig(rig: RigConfig, path: Path) -> None:
    """Write a rig file that :func:`bench.rig.load_rig` reads back to the same configuration."""
    text = "# written by `bench sim serve`: the running simulated twins, seen as a real rig\n" + rig_to_toml(rig)
    path.write_text(text, encoding="utf-8")
