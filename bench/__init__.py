"""dea-bench: test-bench control, simulation and data acquisition for dielectric elastomer actuators."""

from __future__ import annotations


def __getattr__(name: str) -> str:
    """``bench.__version__``, looked up on first use: importlib.metadata costs ~30 ms, and ``bench --help`` and
    every TAB completion import this package without needing the version."""
    if name != "__version__":
        raise AttributeError(f"module 'bench' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        value = version("dea-bench")
    except PackageNotFoundError:  # running from a source tree without installation
        value = "0.0.0+src"
    globals()["__version__"] = value
    return value
