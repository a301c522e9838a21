"""Protocol files (TOML): what to do to the specimen, validated with pydantic.

A protocol names its rig, overrides specimen parameters, says what to record and at what rates, and lists
named steps. Step types (``type = ...``):

* ``waveform`` — periodic set-point on a channel: ``kind`` (sine, raised_cosine, triangle, square),
  ``offset``, ``amplitude``, ``frequency_Hz`` and ``cycles`` or ``duration_s``;
* ``ramp`` — linear ramp of a channel ``to`` a value over ``duration_s``;
* ``hold`` / ``wait`` — keep the set-points for ``duration_s``; ``relax`` — voltage to 0 V over ``ramp_down_s``
  (default: 0.5 s or a tenth of the step, whichever is shorter, but at least 10 set-points, the rig's
  ``limits.shutdown_ramp_s`` and what its amplifier's slew limit allows, at most the step:
  :meth:`bench.protocol.program._Compiler.relax_ramp`), then wait;
* ``move`` — motor go-to ``position`` with ``velocity`` / ``acceleration``;
* ``set`` — change specimen parameters (temperature, hung mass, prototype: an operator action on a real rig);
* ``repeat`` — ``count`` times the nested ``steps``;
* ``sweep`` — the nested ``steps`` for every value of ``over`` (lists or ranges; ``mode`` product or zip),
  with ``{name}`` placeholders in the nested steps replaced by the swept values.

Channels: ``voltage`` (V) and ``position`` (the LS-DEA aperture x, m; the engine maps it to the motor).
Values whose field name carries no unit are quantities with units: ``"7 kV"``, ``"45 mm"``, ``"0.1 m/s"``; a field
whose name carries the unit (``duration_s``, ``frequency_Hz``, ``temperature_K``, ``hung_mass_kg``) takes a plain
number in that unit or a quantity (``"2 min"``, ``"150 g"``, ``"25 °C"``).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    TypeAdapter,
    ValidationError,
    field_validator,
    model_validator,
)

from bench.quantity import format_quantity, parse_quantity, refuse_bool
from bench.tomlfile import first_error, one_line, read_toml, type_hint

Channel = Literal["voltage", "position"]
CHANNEL_DIMENSION = {"voltage": "voltage", "position": "length"}


MAX_STEPS = 100_000  # steps after expanding repeats and sweeps
MAX_NESTING = 20  # repeats and sweeps inside each other
MAX_DURATION_S = 7 * 86_400.0  # one protocol's run time: 7 days
# The shortest step [s]: two set-point periods at the fastest recording.setpoint_Hz (2 kHz). A shorter one has no
# set-point of its own, and a subnormal one (5e-324 s) made ramps divide by it (NaN set-points).
MIN_DURATION_S = 1e-3
RELAX_RAMP_S = 0.5  # a relax step's default ramp to 0 V (or a tenth of the step, whichever is shorter) ...
RELAX_SETPOINTS = 10  # ... but at least this many set-points (program.py, _Compiler.relax_ramp: the full rule)
MAX_EXPANSION = 50_000_000  # characters sweeps may copy while substituting their values
MAX_OPERATOR = 100  # characters of [protocol] operator / `bench run --operator`
MAX_SPECIMEN_ID = 100  # characters of [protocol] specimen_id / `bench run --specimen-id`
MAX_NOTE = 1000  # characters of one note ([protocol] notes / `bench run --note`)
MAX_NOTES = 100  # notes on one run


class _Strict(BaseModel):
    """Base of every protocol table: unknown keys refused, immutable, every float finite (no nan / inf), no true or
    false where a number goes."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _no_bool(cls, data: Any) -> Any:
        """pydantic reads true as 1: ``duration_s = true`` validated as a 1-s step (outside tester). (A model
        validator: a field validator on every field may not touch the steps' discriminator, ``type``.)"""
        if isinstance(data, dict):
            for name, v in data.items():
                if name in cls.model_fields:
                    try:
                        refuse_bool(v, cls.model_fields[name].annotation)
                    except ValueError as exc:
                        raise ValueError(f"{name}: {exc}") from None
        return data


def _q(dimension: str) -> Any:
    def parse(v: Any) -> float:
        return parse_quantity(v, dimension)[0]

    return parse


def _unit_in_name(dimension: str) -> BeforeValidator:
    """A field whose name carries its unit (``duration_s``, ``hung_mass_kg``): a plain number in that unit, or a
    quantity of its dimension with any unit (``"2 min"``, ``"150 g"``, ``"25 °C"``), read by the same parser as
    the quantity fields and converted to the SI unit the name gives; the field's own bounds apply after."""

    def convert(v: Any) -> Any:
        if not isinstance(v, str):
            return v  # numbers (and None) go to the field's own validation
        try:
            return float(v)  # "2": a plain number in the field's unit, as before ("nan" refused by the model)
        except ValueError:
            return parse_quantity(v, dimension)[0]

    return BeforeValidator(convert)


Seconds = Annotated[float, _unit_in_name("time")]
Hertz = Annotated[float, _unit_in_name("frequency")]
MaybeSeconds = Annotated[float | None, _unit_in_name("time")]
MaybeKelvin = Annotated[float | None, _unit_in_name("temperature")]
MaybeKilograms = Annotated[float | None, _unit_in_name("mass")]


class _StepBase(_Strict):
    name: str = ""


class WaveformStep(_StepBase):
    """Periodic set-point on a channel."""

    type: Literal["waveform"]
    channel: Channel = "voltage"
    kind: Literal["sine", "raised_cosine", "triangle", "square"] = "raised_cosine"
    offset: str = "0 V"
    amplitude: str
    frequency_Hz: Hertz = Field(gt=0, le=1000)
    cycles: float | None = Field(None, gt=0, le=MAX_DURATION_S * 1000)
    duration_s: MaybeSeconds = Field(None, ge=MIN_DURATION_S, le=MAX_DURATION_S)

    @model_validator(mode="after")
    def _check(self) -> WaveformStep:
        dim = CHANNEL_DIMENSION[self.channel]
        if self.channel == "position" and self.offset == "0 V":
            object.__setattr__(self, "offset", "0 m")
        parse_quantity(self.offset, dim)
        parse_quantity(self.amplitude, dim)
        if (self.cycles is None) == (self.duration_s is None):
            raise ValueError("give exactly one of cycles or duration_s")
        if not self.duration >= MIN_DURATION_S:
            raise ValueError(f"cycles {self.cycles:g} at frequency_Hz {self.frequency_Hz:g} last "
                             f"{self.duration:.4g} s, below the shortest step of {MIN_DURATION_S:g} s")
        if not self.duration <= MAX_DURATION_S:
            raise ValueError(f"cycles {self.cycles:g} at frequency_Hz {self.frequency_Hz:g} last "
                             f"{self.duration:.4g} s, beyond the limit of {MAX_DURATION_S:.0f} s (7 days)")
        return self

    @property
    def offset_si(self) -> float:
        """Offset in SI units."""
        return parse_quantity(self.offset, CHANNEL_DIMENSION[self.channel])[0]

    @property
    def amplitude_si(self) -> float:
        """Amplitude in SI units."""
        return parse_quantity(self.amplitude, CHANNEL_DIMENSION[self.channel])[0]

    @property
    def duration(self) -> float:
        """Duration [s]."""
        if self.duration_s is not None:
            return self.duration_s
        if self.cycles is None:  # reached only from inside the validator, before its own check has run
            raise ValueError("give exactly one of cycles or duration_s")
        return self.cycles / self.frequency_Hz


class RampStep(_StepBase):
    """Linear ramp of a channel to a value."""

    type: Literal["ramp"]
    channel: Channel = "voltage"
    to: str
    duration_s: Seconds = Field(ge=MIN_DURATION_S, le=MAX_DURATION_S)

    @field_validator("to")
    @classmethod
    def _unit(cls, v: str) -> str:
        parse_quantity(v)
        return v

    @model_validator(mode="after")
    def _dim(self) -> RampStep:
        parse_quantity(self.to, CHANNEL_DIMENSION[self.channel])
        return self

    @property
    def to_si(self) -> float:
        """Target in SI units."""
        return parse_quantity(self.to, CHANNEL_DIMENSION[self.channel])[0]


class HoldStep(_StepBase):
    """Keep the set-points (``hold``/``wait``), or zero the voltage first (``relax``)."""

    type: Literal["hold", "wait", "relax"]
    duration_s: Seconds = Field(ge=MIN_DURATION_S, le=MAX_DURATION_S)
    ramp_down_s: MaybeSeconds = Field(default=None, ge=MIN_DURATION_S, le=MAX_DURATION_S)

    @model_validator(mode="after")
    def _check(self) -> HoldStep:
        if self.ramp_down_s is not None:
            if self.type != "relax":
                raise ValueError(f"ramp_down_s applies to a relax step, not to a {self.type} step")
            if self.ramp_down_s > self.duration_s:
                raise ValueError(f"ramp_down_s = {self.ramp_down_s:g} s is longer than the step's duration_s = "
                                 f"{self.duration_s:g} s")
        return self


class MoveStep(_StepBase):
    """Motor go-to of the LS-DEA aperture."""

    type: Literal["move"]
    position: str
    velocity: str = "0.1 m/s"
    acceleration: str = "1 m/s2"

    @model_validator(mode="after")
    def _check(self) -> MoveStep:
        parse_quantity(self.position, "length")
        if self.velocity_si <= 0 or self.acceleration_si <= 0:
            raise ValueError("velocity and acceleration must be > 0")
        return self

    @property
    def position_si(self) -> float:
        """Target aperture [m]."""
        return parse_quantity(self.position, "length")[0]

    @property
    def velocity_si(self) -> float:
        """Velocity limit [m/s]."""
        return parse_quantity(self.velocity, "velocity")[0]

    @property
    def acceleration_si(self) -> float:
        """Acceleration limit [m/s²]."""
        return parse_quantity(self.acceleration, "acceleration")[0]


class SetStep(_StepBase):
    """Change specimen parameters between tests."""

    type: Literal["set"]
    temperature_K: MaybeKelvin = Field(None, gt=150, lt=450)
    hung_mass_kg: MaybeKilograms = Field(None, ge=0, le=2)
    prototype: Literal[1, 2, 3] | None = None

    @model_validator(mode="after")
    def _some(self) -> SetStep:
        if self.temperature_K is None and self.hung_mass_kg is None and self.prototype is None:
            raise ValueError("a set step needs temperature_K, hung_mass_kg or prototype")
        return self


AnyStep = WaveformStep | RampStep | HoldStep | MoveStep | SetStep
Step = Annotated[AnyStep, Field(discriminator="type")]
STEP_ADAPTER: TypeAdapter[AnyStep] = TypeAdapter(Step)


def nominal_duration(step: AnyStep) -> float:
    """A step's length as written [s]: a move's depends on the rig and a set step takes none, so both count 0."""
    if isinstance(step, WaveformStep):
        return step.duration
    if isinstance(step, RampStep | HoldStep):
        return step.duration_s
    return 0.0


class RecordingConfig(_Strict):
    """What to record and how often (0 switches a stream off)."""

    displacement_Hz: Hertz = Field(10_000.0, ge=0, le=50_000, description="laser data storage rate")
    monitors_Hz: Hertz = Field(5.0, ge=0, le=1000, description="amplifier V and I monitors, polled (the ADAM-4017+ "
                               "converts 10 S/s over its enabled channels: 5 S/s each for V and I)")
    setpoint_Hz: Hertz = Field(50.0, gt=0, le=2000, description="set-point update rate")
    position_Hz: Hertz = Field(100.0, ge=0, le=2000, description="motor position, polled")
    force_Hz: Hertz = Field(100.0, ge=0, le=2000, description="load cell, polled")
    points_per_cycle: int = Field(20, ge=4, le=10_000, description="minimum set-points per waveform cycle")


class SpecimenOverrides(_Strict):
    """Specimen parameters the protocol sets for the whole run (applied to the rig's specimen)."""

    temperature_K: MaybeKelvin = Field(None, gt=150, lt=450)
    hung_mass_kg: MaybeKilograms = Field(None, ge=0, le=2)
    prototype: Literal[1, 2, 3] | None = None


class ProtocolHeader(_Strict):
    """The ``[protocol]`` table."""

    name: str
    description: str = ""
    source: str = ""
    rig: str = Field(description="rig file, relative to the protocol file, or the name of a rig shipped with bench "
                     "(e.g. thesis-sim)", min_length=1, max_length=4096)
    short_variant_of: str = ""
    operator: str | None = Field(None, description=f"who runs it (recorded in the run file; `bench run --operator` "
                                 f"overrides it); one line, at most {MAX_OPERATOR} characters")
    specimen_id: str | None = Field(None, description=f"the specimen's identifier (recorded in the run file; "
                                    f"`bench run --specimen-id` overrides it); one line, at most {MAX_SPECIMEN_ID} "
                                    "characters")
    notes: str | list[str] | None = Field(None, description=f"free notes recorded in the run file (`bench run "
                                          f"--note` adds more); each one line of at most {MAX_NOTE} characters, "
                                          f"at most {MAX_NOTES} notes")

    @field_validator("rig")
    @classmethod
    def _path(cls, v: str) -> str:
        if not v.isprintable():
            raise ValueError("a file path without control characters (NUL, newline, …)")
        return v

    @field_validator("operator")
    @classmethod
    def _operator(cls, v: str | None) -> str | None:
        return None if v is None else check_label(v, MAX_OPERATOR)

    @field_validator("specimen_id")
    @classmethod
    def _specimen_id(cls, v: str | None) -> str | None:
        return None if v is None else check_label(v, MAX_SPECIMEN_ID)

    @field_validator("notes")
    @classmethod
    def _notes(cls, v: str | list[str] | None) -> list[str] | None:
        return None if v is None else check_notes([v] if isinstance(v, str) else v)

    def note_list(self) -> list[str]:
        """The notes as a list (a single string in the file is one note)."""
        return [self.notes] if isinstance(self.notes, str) else list(self.notes or [])


def check_label(text: str, limit: int) -> str:
    """``text`` stripped, if it is non-empty, one line of printable characters and at most ``limit`` long."""
    v = text.strip()
    if not v:
        raise ValueError("empty: give some text or leave the field out")
    if not v.isprintable():
        raise ValueError("one line of printable text (no newline, tab or other control character)")
    if len(v) > limit:
        raise ValueError(f"{len(v)} characters, at most {limit} allowed")
    return v


def check_notes(notes: list[str]) -> list[str]:
    """Each note checked by :func:`check_label` (``MAX_NOTE`` characters), at most ``MAX_NOTES`` of them."""
    if not notes:
        raise ValueError("an empty list: give at least one note or leave the field out")
    if len(notes) > MAX_NOTES:
        raise ValueError(f"{len(notes)} notes, at most {MAX_NOTES} allowed")
    out = []
    for k, note in enumerate(notes):
        try:
            out.append(check_label(note, MAX_NOTE))
        except ValueError as exc:
            raise ValueError(f"note {k + 1}: {exc}") from None
    return out


class Protocol(_Strict):
    """A validated protocol: header, specimen overrides, recording, and the expanded steps in order."""

    protocol: ProtocolHeader
    specimen: SpecimenOverrides = SpecimenOverrides()
    recording: RecordingConfig = RecordingConfig()
    steps: list[Step]
    labels: list[str] = Field(default_factory=list, description="path of each step in the file (sweeps, repeats)")
    text: str = ""
    path: str = ""

    @property
    def sha256(self) -> str:
        """SHA-256 of the file text."""
        return hashlib.sha256(self.text.encode()).hexdigest()

    def rig_path(self) -> Path:
        """Rig file named by the protocol (:func:`resolve_rig_ref`)."""
        return resolve_rig_ref(Path(self.path).parent, self.protocol.rig)


def resolve_rig_ref(folder: Path, ref: str) -> Path:
    """A protocol's ``rig``: a path, resolved against the protocol file's ``folder``; or a bare name with no such
    file there (``rig = "thesis-sim"``: no folder, no ``.toml``) — the rig of that name shipped with bench, found
    wherever bench is installed (what ``bench protocols copy`` writes outside a lab folder: an absolute path into
    site-packages broke when bench was reinstalled). Unknown names resolve as paths (their error names the file)."""
    local = (folder / ref).resolve()
    if local.exists() or "/" in ref or "\\" in ref or ref.endswith(".toml"):
        return local
    from bench.resources import shipped_rigs

    shipped = shipped_rigs().get(ref)
    return shipped.resolve() if shipped is not None else local


def missing_rig_ref(folder: Path, ref: str, takes: str = "a path from the protocol's folder, or a shipped rig's name"
                    ) -> str:
    """Why a protocol's ``rig`` (or ``--rig``) names no rig file (:func:`resolve_rig_ref` from ``folder``), one line:
    the file it looked for, "did you mean" the closest names among the shipped rigs and the rig files in
    ``folder``, its ``rigs/`` or the lab folder's ``rigs/`` above it, and what ``takes`` says it takes."""
    import difflib

    from bench.resources import shipped_rigs

    path = resolve_rig_ref(folder, ref)
    stem = Path(ref.replace("\\", "/")).name.removesuffix(".toml")
    near = {p.stem: p for d in (folder, folder / "rigs", folder.parent / "rigs", path.parent) if d.is_dir()
            for p in d.glob("*.toml")}
    names = sorted({*shipped_rigs(), *near})
    close = difflib.get_close_matches(stem, names, n=1, cutoff=0.75)
    hint = ""
    if close:
        hint = f"; did you mean {near[close[0]] if close[0] in near else close[0]!s}?"
    return f"rig file {path}: not found{hint} ({takes})"


class ProtocolFileError(ValueError):
    """A protocol file that cannot be used (message: one line naming the file and the field)."""

    def __init__(self, message: str) -> None:
        super().__init__(one_line(message))


# ------------------------------------------------------------------ sweep / repeat expansion

_PLACEHOLDER = re.compile(r"\{([A-Za-z_][A-Za-z0-9_]*)\}")


def _substitute(obj: Any, values: dict[str, Any]) -> Any:
    if isinstance(obj, dict):
        return {k: _substitute(v, values) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_substitute(v, values) for v in obj]
    if isinstance(obj, str):
        whole = _PLACEHOLDER.fullmatch(obj)
        if whole and whole.group(1) in values:
            return values[whole.group(1)]  # keeps numbers numeric
        return _PLACEHOLDER.sub(lambda m: str(values.get(m.group(1), m.group(0))), obj)
    return obj


def _number_or_quantity(v: Any, where: str, dim: str | None) -> float:
    """A range bound or step: a finite number (``dim`` None) or a quantity of dimension ``dim``."""
    if dim is None:
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ValueError(f"{where}: give a finite number like the range's start, got {_short(v)}")
        return float(v)
    if not isinstance(v, str):
        raise ValueError(f"{where}: give a quantity with a unit like the range's start, got {_short(v)}")
    try:
        return parse_quantity(v, dim)[0]
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def _same_dimension(where: str, start: str, dim: str, other: str, name: str) -> None:
    """A range's start and its stop (or step) of two dimensions: which is wrong is the writer's to say, so both are
    named (the stop was blamed for a start in hertz in a voltage sweep; an outside tester)."""
    try:
        found = parse_quantity(other)[1]
    except ValueError:
        return  # no quantity at all: the bound's own check says so
    if found != dim:
        raise ValueError(f"{where}: the range's start {_short(start)} is a {dim} and its {name} {_short(other)} a "
                         f"{found}: give start, stop and step in one dimension")


def _range_values(spec: Any, where: str) -> list[Any]:
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: give a list of values or a range {{start, stop, step or num}}, got {_short(spec)}")
    start, stop = spec.get("start"), spec.get("stop")
    if start is None or stop is None or ("step" in spec) == ("num" in spec):
        raise ValueError(f"{where}: a range needs start, stop and one of step or num")
    extra = set(spec) - {"start", "stop", "step", "num"}
    if extra:
        raise ValueError(f"{where}.{sorted(extra)[0]}: a range has only start, stop, step or num")
    dim = None
    if isinstance(start, str):
        try:
            a, dim = parse_quantity(start)
        except ValueError as exc:
            raise ValueError(f"{where}.start: {exc}") from None
    else:
        a = _number_or_quantity(start, f"{where}.start", None)
    if dim is not None and isinstance(stop, str):
        _same_dimension(where, start, dim, stop, "stop")
        if isinstance(spec.get("step"), str):
            _same_dimension(where, start, dim, spec["step"], "step")
    b = _number_or_quantity(stop, f"{where}.stop", dim)
    if "num" in spec:
        num = spec["num"]
        if isinstance(num, bool) or not isinstance(num, int) or not 1 <= num <= MAX_STEPS:
            raise ValueError(f"{where}.num: a whole number from 1 to {MAX_STEPS:,}, got {_short(num)}")
        vals: NDArray[np.floating[Any]] = np.linspace(a, b, num)
    else:
        step = _number_or_quantity(spec["step"], f"{where}.step", dim)
        with np.errstate(all="ignore"):
            span = (b - a) / step if step != 0 else math.nan
        if not math.isfinite(span) or span < 0:
            raise ValueError(f"{where}.step: {_short(spec['step'])} does not lead from start to stop")
        if span + 1 > MAX_STEPS:
            raise ValueError(f"{where}.step: {span + 1:.3g} values exceed the limit of {MAX_STEPS:,}")
        vals = a + step * np.arange(int(np.floor(span + 1e-9)) + 1)
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"{where}: the range's values are not all finite")
    return [format_quantity(float(v), dim) if dim else float(v) for v in vals]


def _short(v: Any, n: int = 40) -> str:
    """``repr(v)`` cut to ``n`` characters, for error messages and labels."""
    text = repr(v) if not isinstance(v, str) else v
    return text if len(text) <= n else text[: n - 1] + "…"


def _size(obj: Any) -> int:
    """Characters of text plus nodes in a TOML value (iterative): the cost of copying it once."""
    n, stack = 0, [obj]
    while stack:
        o = stack.pop()
        n += 1 + (len(o) if isinstance(o, str) else 0)
        if isinstance(o, dict):
            stack.extend(o.values())
        elif isinstance(o, list):
            stack.extend(o)
    return n


def _sweep_values(v: Any, where: str) -> list[Any]:
    vals = v if isinstance(v, list) else _range_values(v, where)
    if not vals:
        raise ValueError(f"{where}: give at least one value")
    for k, x in enumerate(vals):
        if isinstance(x, bool) or not isinstance(x, str | int | float) or (isinstance(x, str) and len(x) > 64):
            raise ValueError(f"{where}[{k}]: swept values are numbers or quantities such as '7 kV', got {_short(x)}")
    return vals


def _inner(step: dict[str, Any], here: str) -> Any:
    inner = step.get("steps")
    if not isinstance(inner, list) or not inner:
        raise ValueError(f"{here}.steps: give at least one nested step")
    return inner


def expand_steps(raw: list[dict[str, Any]], where: str = "steps") -> list[tuple[str, dict[str, Any]]]:
    """Flatten repeats and sweeps into (label, step table) pairs, substituting swept values.

    Bounded before anything is built: at most :data:`MAX_STEPS` steps, :data:`MAX_NESTING` levels of repeats
    and sweeps, and :data:`MAX_EXPANSION` characters copied by sweeps; ValueError (one line) beyond.
    """
    return _expand(raw, where, 0, [0])


def _expand(raw: Any, where: str, depth: int, total: list[int]) -> list[tuple[str, dict[str, Any]]]:
    if depth > MAX_NESTING:
        raise ValueError(f"{_short(where, 80)}: repeats and sweeps nest deeper than {MAX_NESTING} levels")
    if not isinstance(raw, list):
        raise ValueError(f"{_short(where, 80)}: give a list of step tables ([[...steps]]), got {_short(raw)}")
    out: list[tuple[str, dict[str, Any]]] = []

    def count(n: int, field: str) -> None:
        total[0] += n
        if total[0] > MAX_STEPS:
            raise ValueError(f"{_short(field, 80)}: the protocol expands to more than {MAX_STEPS:,} steps")

    for i, step in enumerate(raw):
        here = f"{where}[{i}]"
        if not isinstance(step, dict) or "type" not in step:
            raise ValueError(f"{here}: every step needs a type")
        kind = step["type"]
        label = f"{here}({_short(step.get('name', kind))})"
        if kind == "repeat":
            n = step.get("count")
            if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_STEPS:
                raise ValueError(f"{here}.count: must be a whole number from 1 to {MAX_STEPS:,}")
            inner = _expand(_inner(step, here), f"{here}.steps", depth + 1, total)
            count((n - 1) * len(inner), f"{here}.count")
            for k in range(n):
                out += [(f"{label}#{k + 1}/{lab}", st) for lab, st in inner]
        elif kind == "sweep":
            over = step.get("over")
            if not isinstance(over, dict) or not over:
                raise ValueError(f"{here}.over: give the swept parameters, e.g. over = {{voltage = ['5 kV', '6 kV']}}")
            names = list(over)
            lists = [_sweep_values(v, f"{here}.over.{n}") for n, v in over.items()]
            mode = step.get("mode", "product")
            if mode == "zip":
                if len({len(x) for x in lists}) != 1:
                    raise ValueError(f"{here}: mode = 'zip' needs lists of equal length")
                n_combos = len(lists[0])
            elif mode == "product":
                n_combos = math.prod(len(x) for x in lists)
            else:
                raise ValueError(f"{here}.mode: 'product' or 'zip', got {_short(mode)}")
            inner_raw = _inner(step, here)
            if n_combos > MAX_STEPS or n_combos * _size(inner_raw) > MAX_EXPANSION:
                raise ValueError(f"{here}.over: {n_combos:,} combinations of the nested steps exceed the limit of "
                                 f"{MAX_STEPS:,} steps")
            combos = zip(*lists, strict=True) if mode == "zip" else itertools.product(*lists)
            for combo in combos:
                values = dict(zip(names, combo, strict=True))
                tag = _short(", ".join(f"{n}={v}" for n, v in values.items()), 80)
                for lab, st in _expand(_substitute(inner_raw, values), f"{here}.steps", depth + 1, total):
                    named = dict(st)
                    named["name"] = f"{_short(st.get('name', st['type']))} [{tag}]"
                    out.append((f"{label}[{tag}]/{lab}", named))
        else:
            count(1, here)
            out.append((label, step))
    return out


def _error_line(path: Path, label: str, exc: ValidationError) -> str:
    err, suggestion = first_error(exc.errors(), AnyStep)
    loc = ".".join(str(x) for x in err["loc"] if not str(x).endswith("Step") and x not in
                   ("waveform", "ramp", "hold", "wait", "relax", "move", "set"))
    msg = err["msg"].removeprefix("Value error, ") + type_hint(err) + suggestion
    return f"protocol file {path}: {label}{'.' + loc if loc else ''}: {msg}"


def load_protocol(path: str | Path) -> Protocol:
    """Read, expand and validate a protocol file; raise ProtocolFileError with a one-line message."""
    p = Path(path)
    text, data = read_toml(p, "protocol", ProtocolFileError)
    raw_steps = data.pop("steps", None)
    if not isinstance(raw_steps, list) or not raw_steps:
        raise ProtocolFileError(f"protocol file {p}: steps: give at least one [[steps]] table")
    try:
        expanded = expand_steps(raw_steps)
    except ValueError as exc:
        raise ProtocolFileError(f"protocol file {p}: {exc}") from None
    except (RecursionError, MemoryError):  # bounded above; never let one through as a traceback
        raise ProtocolFileError(f"protocol file {p}: steps: too large or too deeply nested to expand") from None
    steps: list[AnyStep] = []
    total = 0.0
    for label, st in expanded:
        for key, value in st.items():  # every sweep has substituted its values: a placeholder left is a typo
            left = _PLACEHOLDER.search(value) if isinstance(value, str) and key != "name" else None
            if left is not None:
                raise ProtocolFileError(f"protocol file {p}: {label}.{key}: placeholder {left.group(0)} is not "
                                        f"defined: no enclosing sweep's over names {left.group(1)}")
        try:
            steps.append(STEP_ADAPTER.validate_python(st))
        except ValidationError as exc:
            raise ProtocolFileError(_error_line(p, label, exc)) from None
        total += nominal_duration(steps[-1])
        if total > MAX_DURATION_S:
            raise ProtocolFileError(f"protocol file {p}: {label}: the steps up to here last {total:.4g} s, beyond "
                                    f"the limit of {MAX_DURATION_S:.0f} s (7 days)")
    try:
        return Protocol.model_validate({**data, "steps": steps, "labels": [lab for lab, _ in expanded],
                                        "text": text, "path": str(p)})
    except ValidationError as exc:
        err, suggestion = first_error(exc.errors(), Protocol)
        loc = ".".join(str(x) for x in err["loc"])
        raise ProtocolFileError(f"protocol file {p}: {loc}: {err['msg'].removeprefix('Value error, ')}"
                                f"{suggestion}") from None


def json_schema() -> str:
    """JSON schema of the protocol file format (for editors), with the step union and sweep/repeat tables."""
    schema = Protocol.model_json_schema()
    for key in ("labels", "text", "path"):
        schema["properties"].pop(key, None)
    step_ref = schema["properties"]["steps"]["items"]
    container = {"type": "object", "required": ["type", "steps"], "properties": {
        "type": {"enum": ["repeat", "sweep"]}, "name": {"type": "string"}, "count": {"type": "integer", "minimum": 1},
        "over": {"type": "object"}, "mode": {"enum": ["product", "zip"]},
        "steps": {"type": "array", "items": {"$ref": "#/$defs/AnyStep"}}}}
    schema.setdefault("$defs", {})["AnyStep"] = {"anyOf": [step_ref, container]}
    schema["properties"]["steps"]["items"] = {"$ref": "#/$defs/AnyStep"}
    schema["title"] = "dea-bench protocol file"
    _quantity_alternative(schema)
    return json.dumps(schema, indent=2)


UNIT_IN_NAME = ("duration_s", "ramp_down_s", "frequency_Hz", "temperature_K", "hung_mass_kg")


def _quantity_alternative(node: Any) -> None:
    """In the schema, the fields of :data:`UNIT_IN_NAME` (a number in the unit the name gives) also take a quantity
    string (``"2 min"``), as the loader does (:func:`_unit_in_name`)."""
    if isinstance(node, list):
        for item in node:
            _quantity_alternative(item)
        return
    if not isinstance(node, dict):
        return
    for key, value in node.items():
        if key == "properties" and isinstance(value, dict):
            for name in UNIT_IN_NAME:
                prop = value.get(name)
                if isinstance(prop, dict):
                    value[name] = _or_quantity(prop)
        _quantity_alternative(value)


def _or_quantity(prop: dict[str, Any]) -> dict[str, Any]:
    quantity = {"type": "string", "description": "a quantity with a unit of the field's dimension, e.g. '2 min', "
                "'150 g', '25 °C' (converted to the unit in the field's name)"}
    if prop.get("type") == "number":  # required: {type, minimum, maximum, title}
        title = prop.pop("title", None)
        return {"anyOf": [prop, quantity], **({"title": title} if title else {})}
    options = prop.get("anyOf")
    if isinstance(options, list):  # optional: anyOf [number, null]
        prop["anyOf"] = [*options[:1], quantity, *options[1:]] if options[:1] and \
            options[0].get("type") == "number" else options
    return prop
