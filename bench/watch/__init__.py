"""``bench watch``: live plots of run files in a browser (server-side min/max decimation, pause and stop only)."""

from __future__ import annotations

import socket


def free_port(port: int = 0) -> int:
    """``port`` if it is free on the loopback now, else a one-line error; 0: any free port (``bench run --web``,
    the benchmark)."""
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError as exc:
            raise ValueError(f"cannot serve on 127.0.0.1:{port}: {exc.strerror or exc} (--web-port N, or 0)") from None
        found: int = s.getsockname()[1]
        return found
