"""Checking a rig's instruments, and writing a rig file that points at running simulated twins."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from bench.rig import RigConfig, rig_to_toml
from bench.runtime.instruments import build_instruments
from drivers.errors import InstrumentError
from drivers.interfaces import Instrument


@dataclass(frozen=True)
class CheckRow:
    """Outcome of checking one instrument."""

    role: str
    ok: bool
    identity: str = ""
    state: str = ""
    reading: str = ""
    error: str = ""


def _fmt(value: float, unit: str, scale: float = 1.0, digits: int = 4) -> str:
    return "n/a" if not math.isfinite(value) else f"{value * scale:.{digits}g} {unit}"


def _probe(role: str, drv: Instrument) -> tuple[str, str]:
    """(state, first reading) of one connected instrument."""
    if role == "amplifier":
        v, i = drv.read_monitors()  # type: ignore[attr-defined]
        return (f"set-point {drv.commanded:.0f} V, limit ±{drv.max_voltage:.0f} V",  # type: ignore[attr-defined]
                f"{_fmt(v.value, 'V', digits=5)}, {_fmt(i.value, 'µA', 1e6)}")
    if role == "laser":
        r = drv.read()  # type: ignore[attr-defined]
        return ("general mode", _fmt(r.value, "mm", 1e3, 6) if r.ok else r.status)
    if role == "motor":
        s = drv.status()  # type: ignore[attr-defined]
        flags = ", ".join(f for f, on in (("homed", s.homed), ("moving", s.moving), ("error", s.error)) if on)
        return (s.state + (f" ({flags})" if flags else ""), _fmt(s.position, "mm", 1e3, 6))
    if role == "daq":
        ain0 = drv.read_ain(0)  # type: ignore[attr-defined]
        return ("stream running" if drv.streaming else "idle", f"AIN0 {_fmt(ain0.value, 'V', digits=5)}")  # type: ignore[attr-defined]
    r = drv.read()  # type: ignore[attr-defined]
    return ("stable" if r.ok else r.status, _fmt(r.value, "N", digits=4))


def check_instruments(rig: RigConfig, endpoints: dict[str, str] | None = None) -> list[CheckRow]:
    """Connect to every instrument, identify it, read it once, leave it safe; one row per instrument."""
    inst = build_instruments(rig, endpoints)
    rows: list[CheckRow] = []
    try:
        for role, drv in inst.items():
            try:
                drv.connect()
                ident = str(drv.identify())
                state, reading = _probe(role, drv)
                rows.append(CheckRow(role, True, ident, state, reading))
            except InstrumentError as exc:
                rows.append(CheckRow(role, False, error=str(exc)))
    finally:
        for err in inst.close():
            rows.append(CheckRow("close", False, error=err))
    return rows


def served_rig(rig: RigConfig, ports: dict[str, str]) -> RigConfig:
    """The rig as seen from outside: real (not simulated), ports set to the running twins' endpoints."""
    data = rig.model_dump()
    data["simulated"] = False
    data["name"] = f"{rig.name}-served"
    for name, port in ports.items():
        if name in data.get("buses", {}):
            data["buses"][name]["port"] = port
        elif data.get(name) is not None:
            data[name]["port"] = port
    return RigConfig.model_validate(data)


def write_rig(rig: RigConfig, path: Path) -> None:
    """Write a rig file that :func:`bench.rig.load_rig` reads back to the same configuration."""
    text = "# written by `bench sim serve`: the running simulated twins, seen as a real rig\n" + rig_to_toml(rig)
    path.write_text(text, encoding="utf-8")
