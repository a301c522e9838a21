"""Help pages show their units: bracketed text such as ``[s]``, ``[kg]``, ``[mm]`` is not taken as rich markup."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from bench.cli import app

runner = CliRunner()
BRACKETED = re.compile(r"\[[^\[\]]+\]")


def _commands(cmd: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    yield path, cmd
    if hasattr(cmd, "commands"):  # a group (typer vendors click: no click import)
        for name, sub in sorted(cmd.commands.items()):
            if not sub.hidden:
                yield from _commands(sub, (*path, name))


def _flat(text: str) -> str:
    """Help output without the panels' box characters and line breaks (rich wraps long help texts)."""
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", text).split())


COMMANDS = list(_commands(typer.main.get_command(app)))


def test_the_known_units_are_shown() -> None:
    """The cases of the issue: ``--duration`` lost ``[s]``, ``--mass``/``--position``/``--stroke`` ``[kg]``/``[mm]``."""
    out = _flat(runner.invoke(app, ["simulate", "thesis", "--help"], terminal_width=200).output)
    assert "Simulated time [s]." in out
    out = _flat(runner.invoke(app, ["simulate", "lsdea", "--help"], terminal_width=200).output)
    assert "Hung mass [kg] (isotonic)." in out and "Blocked aperture [mm] (isometric)." in out
    assert "[mm] (isopotential)" in out


@pytest.mark.parametrize("path", [p for p, _ in COMMANDS], ids=lambda p: " ".join(p) or "bench")
def test_every_help_page_keeps_its_bracketed_text(path: tuple[str, ...]) -> None:
    cmd = dict(COMMANDS)[path]
    texts = [cmd.help or ""] + [getattr(p, "help", None) or "" for p in cmd.params]
    wanted = {m for t in texts for m in BRACKETED.findall(" ".join(t.split()))}
    res = runner.invoke(app, [*path, "--help"], terminal_width=200)
    assert res.exit_code == 0, res.output
    out = _flat(res.output)
    missing = sorted(w for w in wanted if w not in out)
    assert not missing, f"bench {' '.join(path)} --help lost {missing}"


@pytest.mark.parametrize("value, unit, shown", [
    (6000.0, "V", "6 kV"), (3.2e-5, "A", "32 µA"), (0.1, "m", "100 mm"), (-1.05, "N", "-1.05 N"),
    (0.0, "m", "0 m"), (-1.4e-14, "A", "-0.000 nA"),
])
def test_values_are_shown_with_an_si_prefix(value: float, unit: str, shown: str) -> None:
    """Live view and devices check show the drivers' SI values with a prefix (1–3 digits before the point)."""
    from bench.units import si

    assert si(value, unit) == shown
