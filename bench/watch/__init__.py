"""``bench watch``: live plots of run files in a browser (server-side min/max decimation, pause and stop only)."""

from __future__ import annotations

import socket


def free_port() -> int:
    """A port free on the loopback now (``bench run --web --web-port 0``, the benchmark)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port
