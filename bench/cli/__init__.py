"""The ``bench`` command line (typer + rich).

The app is built here: each command module defines its commands and a ``register`` function that puts them on the
app; none imports the app back (tests/test_layers.py). A command parses its options, calls one use case of
bench/app and renders the result (tests/test_cli_thin.py). Entry point: ``bench = "bench.cli:app"``.
"""

from __future__ import annotations

import typer

from bench.cli import analysis, catalog, lab, main, run, watch

__all__ = ["app"]

# rich_markup_mode=None: help texts are plain text ("Simulated time [s]." keeps its unit)
app = typer.Typer(name="bench", help="dea-bench: DEA test-bench control, simulation and data acquisition.",
                  no_args_is_help=True, pretty_exceptions_enable=False, add_completion=True, rich_markup_mode=None)
groups = main.register(app)  # the main options; simulate, sim, devices; benchmark
analysis.register(app)  # fit, design-map, report, demo
lab.register(app, devices=groups["devices"])  # export; devices control
run.register(app)  # validate, run, inspect, recover, init; protocols
catalog.register(app)  # runs list, specimen show, catalog rebuild
watch.register(app)  # watch (live plots in a browser)
