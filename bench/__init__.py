"""dea-bench: test-bench control, simulation and data acquisition for dielectric elastomer actuators."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dea-bench")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+src"
