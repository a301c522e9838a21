"""Protocol files (TOML): what to do to the specimen, validated with pydantic.

A protocol names its rig, overrides specimen parameters, says what to record and at what rates, and lists
named steps. Step types (``type = ...``):

* ``waveform`` — periodic set-point on a channel: ``kind`` (sine, raised_cosine, triangle, square),
  ``offset``, ``amplitude``, ``frequency_Hz`` and ``cycles`` or ``duration_s``;
* ``ramp`` — linear ramp of a channel ``to`` a value over ``duration_s``;
* ``hold`` / ``wait`` — keep the set-points for ``duration_s``; ``relax`` — voltage to 0 V, then wait;
* ``move`` — motor go-to ``position`` with ``velocity`` / ``acceleration``;
* ``set`` — change specimen parameters (temperature, hung mass, prototype: an operator action on a real rig);
* ``repeat`` — ``count`` times the nested ``steps``;
* ``sweep`` — the nested ``steps`` for every value of ``over`` (lists or ranges; ``mode`` product or zip),
  with ``{name}`` placeholders in the nested steps replaced by the swept values.

Channels: ``voltage`` (V) and ``position`` (the LS-DEA aperture x, m; the engine maps it to the motor).
Values whose field name carries no unit are quantities with units: ``"7 kV"``, ``"45 mm"``, ``"0.1 m/s"``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, field_validator, model_validator

from bench.protocol.quantity import format_quantity, parse_quantity
from bench.tomlfile import read_toml

Channel = Literal["voltage", "position"]
CHANNEL_DIMENSION = {"voltage": "voltage", "position": "length"}


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _q(dimension: str) -> Any:
    def parse(v: Any) -> float:
        return parse_quantity(v, dimension)[0]

    return parse


class _StepBase(_Strict):
    name: str = ""


class WaveformStep(_StepBase):
    """Periodic set-point on a channel."""

    type: Literal["waveform"]
    channel: Channel = "voltage"
    kind: Literal["sine", "raised_cosine", "triangle", "square"] = "raised_cosine"
    offset: str = "0 V"
    amplitude: str
    frequency_Hz: float = Field(gt=0, le=1000)
    cycles: float | None = Field(None, gt=0)
    duration_s: float | None = Field(None, gt=0)

    @model_validator(mode="after")
    def _check(self) -> WaveformStep:
        dim = CHANNEL_DIMENSION[self.channel]
        if self.channel == "position" and self.offset == "0 V":
            object.__setattr__(self, "offset", "0 m")
        parse_quantity(self.offset, dim)
        parse_quantity(self.amplitude, dim)
        if (self.cycles is None) == (self.duration_s is None):
            raise ValueError("give exactly one of cycles or duration_s")
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
        return self.duration_s if self.duration_s is not None else self.cycles / self.frequency_Hz  # type: ignore[operator]


class RampStep(_StepBase):
    """Linear ramp of a channel to a value."""

    type: Literal["ramp"]
    channel: Channel = "voltage"
    to: str
    duration_s: float = Field(gt=0)

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
    duration_s: float = Field(gt=0)


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
    temperature_K: float | None = Field(None, gt=150, lt=450)
    hung_mass_kg: float | None = Field(None, ge=0, le=2)
    prototype: Literal[1, 2, 3] | None = None

    @model_validator(mode="after")
    def _some(self) -> SetStep:
        if self.temperature_K is None and self.hung_mass_kg is None and self.prototype is None:
            raise ValueError("a set step needs temperature_K, hung_mass_kg or prototype")
        return self


Step = Annotated[WaveformStep | RampStep | HoldStep | MoveStep | SetStep, Field(discriminator="type")]
STEP_ADAPTER: TypeAdapter[Any] = TypeAdapter(Step)


class RecordingConfig(_Strict):
    """What to record and how often (0 switches a stream off)."""

    displacement_Hz: float = Field(10_000.0, ge=0, le=50_000, description="laser data storage rate")
    monitors_Hz: float = Field(5.0, ge=0, le=1000, description="amplifier V and I monitors, polled (the ADAM-4017+ "
                               "converts 10 S/s over its enabled channels: 5 S/s each for V and I)")
    setpoint_Hz: float = Field(50.0, gt=0, le=2000, description="set-point update rate")
    position_Hz: float = Field(100.0, ge=0, le=2000, description="motor position, polled")
    force_Hz: float = Field(100.0, ge=0, le=2000, description="load cell, polled")
    points_per_cycle: int = Field(20, ge=4, le=10_000, description="minimum set-points per waveform cycle")


class SpecimenOverrides(_Strict):
    """Specimen parameters the protocol sets for the whole run (applied to the rig's specimen)."""

    temperature_K: float | None = Field(None, gt=150, lt=450)
    hung_mass_kg: float | None = Field(None, ge=0, le=2)
    prototype: Literal[1, 2, 3] | None = None


class ProtocolHeader(_Strict):
    """The ``[protocol]`` table."""

    name: str
    description: str = ""
    source: str = ""
    rig: str = Field(description="rig file, relative to the protocol file")
    short_variant_of: str = ""


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
        """Rig file named by the protocol, resolved against the protocol file's folder."""
        return (Path(self.path).parent / self.protocol.rig).resolve()


class ProtocolFileError(ValueError):
    """A protocol file that cannot be used (message: one line naming the file and the field)."""


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


def _range_values(spec: dict[str, Any], where: str) -> list[Any]:
    start, stop = spec.get("start"), spec.get("stop")
    if start is None or stop is None or ("step" in spec) == ("num" in spec):
        raise ValueError(f"{where}: a range needs start, stop and one of step or num")
    dim = None
    if isinstance(start, str):
        a, dim = parse_quantity(start)
        b = parse_quantity(stop, dim)[0]
    else:
        a, b = float(start), float(stop)
    if "num" in spec:
        vals = np.linspace(a, b, int(spec["num"]))
    else:
        step = parse_quantity(spec["step"], dim)[0] if dim else float(spec["step"])
        if step == 0 or (b - a) / step < 0:
            raise ValueError(f"{where}: step {spec['step']!r} does not lead from start to stop")
        vals = a + step * np.arange(int(np.floor((b - a) / step + 1e-9)) + 1)
    return [format_quantity(float(v), dim) if dim else float(v) for v in vals]


def expand_steps(raw: list[dict[str, Any]], where: str = "steps") -> list[tuple[str, dict[str, Any]]]:
    """Flatten repeats and sweeps into (label, step table) pairs, substituting swept values."""
    out: list[tuple[str, dict[str, Any]]] = []
    for i, step in enumerate(raw):
        here = f"{where}[{i}]"
        if not isinstance(step, dict) or "type" not in step:
            raise ValueError(f"{here}: every step needs a type")
        kind = step["type"]
        label = f"{here}({step.get('name', kind)})"
        if kind == "repeat":
            count = step.get("count")
            if not isinstance(count, int) or count < 1:
                raise ValueError(f"{here}.count: must be a whole number ≥ 1")
            inner = expand_steps(step.get("steps", []), f"{here}.steps")
            for k in range(count):
                out += [(f"{label}#{k + 1}/{lab}", st) for lab, st in inner]
        elif kind == "sweep":
            over = step.get("over")
            if not isinstance(over, dict) or not over:
                raise ValueError(f"{here}.over: give the swept parameters, e.g. over = {{voltage = ['5 kV', '6 kV']}}")
            names = list(over)
            lists = [v if isinstance(v, list) else _range_values(v, f"{here}.over.{n}") for n, v in over.items()]
            mode = step.get("mode", "product")
            if mode == "zip":
                if len({len(x) for x in lists}) != 1:
                    raise ValueError(f"{here}: mode = 'zip' needs lists of equal length")
                combos = list(zip(*lists, strict=True))
            elif mode == "product":
                combos = list(itertools.product(*lists))
            else:
                raise ValueError(f"{here}.mode: 'product' or 'zip', got {mode!r}")
            inner_raw = step.get("steps", [])
            for combo in combos:
                values = dict(zip(names, combo, strict=True))
                tag = ", ".join(f"{n}={v}" for n, v in values.items())
                for lab, st in expand_steps(_substitute(inner_raw, values), f"{here}.steps"):
                    named = dict(st)
                    named["name"] = f"{st.get('name', st['type'])} [{tag}]"
                    out.append((f"{label}[{tag}]/{lab}", named))
        else:
            out.append((label, step))
    return out


def _error_line(path: Path, label: str, exc: ValidationError) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(x) for x in err["loc"] if not str(x).endswith("Step") and x not in
                   ("waveform", "ramp", "hold", "wait", "relax", "move", "set"))
    msg = err["msg"].removeprefix("Value error, ")
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
    steps = []
    for label, st in expanded:
        try:
            steps.append(STEP_ADAPTER.validate_python(st))
        except ValidationError as exc:
            raise ProtocolFileError(_error_line(p, label, exc)) from None
    try:
        return Protocol.model_validate({**data, "steps": steps, "labels": [lab for lab, _ in expanded],
                                        "text": text, "path": str(p)})
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(x) for x in err["loc"])
        raise ProtocolFileError(f"protocol file {p}: {loc}: {err['msg'].removeprefix('Value error, ')}") from None


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
    return json.dumps(schema, indent=2)
