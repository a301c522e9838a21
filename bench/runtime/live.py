"""Rich live view of a running protocol: bounded, refreshed at a fixed rate from the engine's snapshot.

The quantities shown and their units come from the run's stream layout — the instruments' ``describe()``
(:func:`units_of`) — not from a list here: a new instrument's readings appear with the unit its driver declares.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from rich.console import Group, RenderableType
from rich.markup import escape
from rich.panel import Panel
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from bench.runtime.context import Snapshot
from bench.units import si
from drivers.interfaces import DataKey


def units_of(streams: Mapping[str, Sequence[DataKey]]) -> dict[str, str]:
    """Snapshot key → SI unit from the recorder's layout (a column's name; ``setpoint``: the set-points' voltage)."""
    units = {k.name: k.unit for keys in streams.values() for k in keys if k.unit not in ("1", "s")}
    for k in streams.get("setpoints", ()):
        if k.name == "voltage":
            units["setpoint"] = k.unit
    return units


def _hms(seconds: float) -> str:
    seconds = max(0, round(seconds))
    return f"{seconds // 3600:d}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}"


UNDER_WAY = ("starting", "running", "paused", "manual")  # Snapshot.state while a run goes on


class LiveView:
    """Renders a :class:`Snapshot`; the ETA comes from the observed speed (virtual time runs faster)."""

    def __init__(self, title: str, snapshot: Snapshot, units: Mapping[str, str], keys: str = "") -> None:
        """``keys``: the key help shown under the panel ('' when the view takes no keys)."""
        self.title = title
        self.snapshot = snapshot
        self.units = dict(units)
        self.keys = keys
        self._wall0 = time.monotonic()

    def __rich__(self) -> Panel:
        s = self.snapshot
        frac = s.t / s.duration if s.duration > 0 else 0.0
        wall = time.monotonic() - self._wall0
        speed = s.t / wall if wall > 0 and s.t > 0 else 0.0
        ended = s.state not in UNDER_WAY  # a run that ended has no time left: no ETA from its speed before the end
        eta = (s.duration - s.t) / speed if speed > 0 and not ended else float("nan")
        head = Text.assemble((f"step {s.step + 1}/{s.steps} ", "bold"), s.step_name[:70])
        progress = Table.grid(padding=(0, 1))
        progress.add_row(ProgressBar(total=1.0, completed=min(frac, 1.0), width=40),
                         f"{100 * frac:5.1f} %  run {_hms(s.t)} / {_hms(s.duration)}",
                         escape(f"ETA {_hms(eta) if eta == eta else '–'}  ({speed:.1f}× real time)  [{s.state}]"))
        values = Table.grid(padding=(0, 2))
        cells = []
        for key, value in list(s.values.items()):
            if key in self.units:
                number, _, unit = si(value, self.units[key]).partition(" ")
                cells.append(f"{key} [bold]{number}[/] {unit}")
        if cells:
            values.add_row(*cells)
        headroom = Table.grid(padding=(0, 2))
        hr = [f"{k} {100 * v:3.0f} %" if v < 0.9 else f"[red]{k} {100 * v:3.0f} %[/]" for k, v in s.headroom.items()]
        if hr:
            headroom.add_row("limits used:", *hr)
        parts: list[RenderableType] = [head, progress, values, headroom]
        if s.state == "paused":
            parts.append(Text("PAUSED: output at 0 V, motor held, recording goes on", style="bold yellow"))
        if self.keys:
            parts.append(Text(self.keys, style="dim"))
        return Panel(Group(*parts), title=self.title, border_style="yellow" if s.state == "paused" else "cyan")


class Keys:
    """Single keys typed at the live view, without Enter (the terminal in cbreak mode while it runs): ``actions``
    maps a key to what it does. A context manager; restores the terminal on exit. Does nothing unless stdin is a
    terminal (a pipe or a file is never read)."""

    def __init__(self, actions: Mapping[str, Callable[[], None]]) -> None:
        self.actions = dict(actions)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._saved: list[Any] | None = None

    def __enter__(self) -> Keys:
        if not sys.stdin.isatty():
            return self
        import termios
        import tty

        fd = sys.stdin.fileno()
        self._saved = termios.tcgetattr(fd)
        tty.setcbreak(fd)
        self._thread = threading.Thread(target=self._read, args=(fd,), name="live-keys", daemon=True)
        self._thread.start()
        return self

    def _read(self, fd: int) -> None:
        import os
        import select

        while not self._stop.is_set():
            ready, _, _ = select.select([fd], [], [], 0.1)
            if not ready:
                continue
            try:
                ch = os.read(fd, 1).decode("utf-8", "replace").lower()
            except OSError:
                return
            action = self.actions.get(ch)
            if action is not None:
                action()

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        if self._saved is not None:
            import termios

            termios.tcsetattr(sys.stdin.fileno(), termios.TCSADRAIN, self._saved)
