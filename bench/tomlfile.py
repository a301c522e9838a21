"""Reading the bench's TOML files (rig and protocol files) with one-line errors that name the file."""

from __future__ import annotations

import tomllib
from pathlib import Path


def read_toml(path: Path, kind: str, error: type[Exception]) -> tuple[str, dict]:
    """(text, parsed table) of a TOML file; raise ``error("<kind> file <path>: …")`` if it cannot be."""
    try:
        text = path.read_text(encoding="utf-8")
        return text, tomllib.loads(text)
    except FileNotFoundError:
        raise error(f"{kind} file {path}: not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{kind} file {path}: cannot be read ({exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{kind} file {path}: not valid TOML ({exc})") from None
