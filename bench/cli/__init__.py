"""The ``bench`` command line (typer + rich).

The app is built here: each command module defines its commands and a ``register`` function that puts them on the
app; none imports the app back (tests/test_layers.py). A command parses its options, calls one use case of
bench/app and renders the result (tests/test_cli_thin.py). Entry point: ``bench = "bench.cli:app"``.
"""

from __future__ import annotations

from typing import Any

import typer
from typer.core import TyperGroup

from bench.cli import analysis, catalog, lab, main, run, watch
from bench.cli.common import fail

__all__ = ["app"]


class _NoEmptyArguments(TyperGroup):
    """The command line refuses an empty argument (``--out ''``, ``--out=``, ``report ''``: an unset shell variable,
    most often) in one line naming it: a path option took it as the current folder (outside tester), and no option
    or argument of bench means anything by an empty value."""

    def parse_args(self, ctx: Any, args: list[str]) -> list[str]:
        for i, arg in enumerate([] if ctx.resilient_parsing else args):  # (completion parses what is typed so far)
            if arg == "--":
                break
            if arg == "" or (arg.startswith("--") and arg.endswith("=")):
                before = args[i - 1] if i else ""
                valued = before.startswith("-") and before not in self._flags(ctx, args[:i - 1])
                named = arg[:-1] if arg else before if valued else f"argument {i + 1} of the command line"
                raise fail(f"{named}: empty (an unset shell variable?): give it a value")
        return super().parse_args(ctx, args)

    def _flags(self, ctx: Any, args: list[str]) -> set[str]:
        """The names of the options that take no value (``--yes``) of the command ``args`` lead to: an empty word
        after one is an argument of its own (``--yes ''`` was named "--yes: empty", a reviewer)."""
        command: Any = self
        for arg in args:
            sub = command.get_command(ctx, arg) if hasattr(command, "get_command") else None
            if sub is not None:
                command = sub
        return {name for param in command.params if getattr(param, "is_flag", False) or getattr(param, "count", False)
                for name in (*param.opts, *param.secondary_opts)}


# rich_markup_mode=None: help texts are plain text ("Simulated time [s]." keeps its unit)
app = typer.Typer(name="bench", help="dea-bench: DEA test-bench control, simulation and data acquisition.",
                  no_args_is_help=True, pretty_exceptions_enable=False, add_completion=True, rich_markup_mode=None,
                  cls=_NoEmptyArguments)
groups = main.register(app)  # the main options; simulate, sim, devices; benchmark
analysis.register(app)  # fit, design-map, report, demo
lab.register(app, devices=groups["devices"])  # export; devices control
run.register(app)  # validate, run, inspect, recover, init; protocols
catalog.register(app)  # runs list, specimen show, catalog rebuild
watch.register(app)  # watch (live plots in a browser)
