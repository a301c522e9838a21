"""The application layer: one call per use case (plan and execute a run, inspect run files, the design map, a
report, the simulations, the simulated rig served, a manual-control session).

Each use case takes plain arguments (paths, numbers in SI units, names) and, where it lasts, an optional progress
callback; it returns a result dataclass and prints nothing. The command line (bench/cli) parses, calls one of
these and renders the result (tables, JSON); nothing else imports this package (tests/test_layers.py).

Light at the top: ``bench --help`` imports the command modules, which import these modules inside their commands;
the modules here load numpy, h5py, the run time … inside their functions too.
"""

from __future__ import annotations

from collections.abc import Callable

Progress = Callable[[float], None]
"""Called with the fraction done (0 … 1) of a use case that lasts."""

__all__ = ["Progress"]
