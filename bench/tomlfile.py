"""Reading the bench's TOML files (rig and protocol files) with one-line errors that name the file.

Input is bounded here, before anything else looks at it: a regular file of at most :data:`MAX_FILE_BYTES` and
tables/arrays nested at most :data:`MAX_DEPTH` deep (the parser itself recurses; a file nested deeper
than Python's recursion limit is reported as too deep, not as a RecursionError).
"""

from __future__ import annotations

import stat
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

MAX_FILE_BYTES = 4_000_000  # the shipped files are a few kB
# the units field names end in (rig and protocol files): `max_voltage_V` takes a number in V, `laser_m_per_V` in m/V
UNIT_SUFFIXES = ("Hz", "kg", "mm", "s", "m", "V", "A", "N", "K")
# protocol fields that take a quantity as a string with its unit (bench/protocol/schema.py: parse_quantity)
QUANTITY_FIELDS = ("offset", "amplitude", "to", "position", "velocity", "acceleration")
MAX_DEPTH = 64  # tables and arrays; a protocol's repeats and sweeps nest ≤ 20 deep (2 levels each)


def one_line(message: str, limit: int = 400) -> str:
    """``message`` on one line (control characters escaped) and at most ``limit`` characters."""
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in message)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _unit_of(field: str) -> str | None:
    """The unit a field's name ends in (``max_voltage_V``: V; ``laser_m_per_V``: m/V), None if it names none."""
    head, per, tail = field.rpartition("_per_")
    if per:
        num = head.rpartition("_")[2]
        return f"{num}/{tail.replace('_per_', '/')}" if num in UNIT_SUFFIXES and tail.rstrip("2") in UNIT_SUFFIXES \
            else None
    last = field.rpartition("_")[2]
    return last if "_" in field and last in UNIT_SUFFIXES else None


BOUNDS = ("less_than_equal", "less_than", "greater_than_equal", "greater_than")  # pydantic's bound errors


def type_hint(err: Mapping[str, Any]) -> str:
    """What to write instead, for a pydantic error of a value of the wrong TOML type ("" if none applies): a string
    that is no number where a field takes a plain number (one whose name ends in its unit reads a quantity with its
    unit first: bench.rig, bench.protocol.schema), or a number where a protocol quantity (``QUANTITY_FIELDS``)
    takes a string with its unit (``amplitude = "5 kV"``); for a bound of a field whose name ends in its unit, that
    unit and the value given, converted to it ("less than or equal to 10 s (got 3600 s)")."""
    field, value = (err.get("loc") or ("",))[-1], err.get("input")
    if not isinstance(field, str):
        return ""
    if err.get("type") in BOUNDS and (unit := _unit_of(field)) is not None and isinstance(value, int | float) \
            and not isinstance(value, bool):  # the bound in the field's unit, and the value given once converted
        return f" {unit} (got {value:g} {unit})"  # (an outside tester: "1 h" said only "less than or equal to 10")
    if err.get("type") in ("float_parsing", "int_parsing", "float_type", "int_type") and isinstance(value, str):
        unit = _unit_of(field)
        where = f" in {unit}, the unit its name ends in" if unit else ""
        return f' (got "{one_line(value, 40)}": write a plain number{where}, without quotes)'
    if err.get("type") == "string_type" and field in QUANTITY_FIELDS and isinstance(value, int | float) \
            and not isinstance(value, bool):
        return f' (got {value!r}: write the value with its unit, in quotes, e.g. {field} = "{value!r} <unit>")'
    return ""


def first_error(errors: list[Any], root: Any) -> tuple[Any, str]:
    """The error to report of a pydantic validation (``errors``: ``exc.errors()``, ``root``: the model, union or
    annotation validated) and what to add to its message: the first, unless a field is unknown and close to one
    the table takes (a typo, which pydantic reports after the "Field required" of the field meant): that one, with
    "; did you mean NAME?" (difflib against the allowed fields)."""
    import difflib

    for err in errors:
        loc = err.get("loc") or ()
        if err.get("type") == "extra_forbidden" and loc and isinstance(loc[-1], str):
            match = difflib.get_close_matches(loc[-1], allowed_fields(root, loc[:-1]), n=1, cutoff=0.6)
            if match:
                return err, f"; did you mean {match[0]}?"
    return errors[0], ""


def allowed_fields(root: Any, path: tuple[Any, ...]) -> list[str]:
    """The field names (aliases where set) a table at ``path`` (a pydantic error's ``loc``) of ``root`` takes: the
    fields followed down through the models in each annotation (unions, lists, optionals), a discriminated union's
    tag picking the model whose ``type`` it is; [] where the path leaves the models."""
    from typing import Literal, get_args, get_origin

    from pydantic import BaseModel

    def models(tp: Any) -> list[type[BaseModel]]:
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            return [tp]
        return [m for a in get_args(tp) for m in models(a)]

    def tags(m: type[BaseModel]) -> tuple[object, ...]:
        """Every ``type`` the model is tagged with (a hold step is also ``wait`` and ``relax``)."""
        f = m.model_fields.get("type")
        return get_args(f.annotation) if f is not None and get_origin(f.annotation) is Literal else ()

    level = models(root)
    for key in path:
        if isinstance(key, int):  # a list's index: its items' models are already in the level
            continue
        level = [n for m in level for n in (models(m.model_fields[key].annotation) if key in m.model_fields
                                            else [m] if key in tags(m) else [])]
    return sorted({f.alias or name for m in level for name, f in m.model_fields.items()})


def _too_deep(data: Any, limit: int) -> str | None:
    """Dotted path of the first value nested deeper than ``limit`` (iterative: no recursion), or None."""
    stack: list[tuple[Any, str, int]] = [(data, "", 0)]
    while stack:
        obj, where, depth = stack.pop()
        if depth > limit:
            return where or "(top level)"
        if isinstance(obj, dict):
            stack.extend((v, f"{where}.{k}" if where else str(k), depth + 1) for k, v in obj.items())
        elif isinstance(obj, list):
            stack.extend((v, f"{where}[{i}]", depth + 1) for i, v in enumerate(obj))
    return None


def read_toml(path: Path, kind: str, error: type[Exception]) -> tuple[str, dict[str, Any]]:
    """(text, parsed table) of a TOML file; raise ``error("<kind> file <path>: …")`` if it cannot be."""
    try:
        if not stat.S_ISREG(path.stat().st_mode):  # /dev/zero or a FIFO would be read forever
            raise error(f"{kind} file {path}: not a regular file")
        with path.open("rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
        if len(raw) > MAX_FILE_BYTES:
            raise error(f"{kind} file {path}: larger than {MAX_FILE_BYTES:,} bytes")
        text = raw.decode("utf-8").replace("\r\n", "\n").replace("\r", "\n")  # as read_text() would
    except FileNotFoundError:
        raise error(f"{kind} file {path}: not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{kind} file {path}: cannot be read ({exc})") from None
    except ValueError as exc:  # e.g. a NUL in the path
        if isinstance(exc, error):
            raise
        raise error(f"{kind} file {path}: cannot be read ({exc})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{kind} file {path}: not valid TOML ({exc})") from None
    except RecursionError:
        raise error(f"{kind} file {path}: arrays or tables nested too deeply to parse "
                    f"(at most {MAX_DEPTH} levels)") from None
    deep = _too_deep(data, MAX_DEPTH)
    if deep is not None:
        where = deep if len(deep) <= 80 else deep[:40] + "…" + deep[-37:]
        raise error(f"{kind} file {path}: {where}: nested deeper than {MAX_DEPTH} levels")
    return text, data
