"""Fuzzing the rig and protocol files: every mutant is refused in one line, or accepted — never a traceback or a hang.

A seeded mutator derives files from the shipped ones (``protocols/short/*.toml`` and ``rigs/*.toml`` by
default): values replaced by nan, inf, -1, 0, huge numbers, strings, arrays or tables; keys deleted or added;
tables duplicated; repeats and arrays nested deep; huge sweeps and repeats; long holds; another rig; the
text truncated or sprinkled with random bytes. Each file goes the way of ``bench validate`` (load → compile →
dry run, :func:`bench.runtime.run.plan_run`) in a worker process with a hard time limit per file (the worker is
killed when it runs over, so a hang is counted, not endured), and is classified:

* ``refused`` — a ``ValueError``/``OSError`` whose message is one line naming the file (what the CLI prints);
* ``accepted`` — validated and dry-run;
* ``traceback`` — any other exception, or a refusal whose message is not one line naming the file;
* ``hang`` — still running after the time limit (default 10 s).

``python -m tests.fuzzing.files --protocols N --rigs N --seed S`` (from the repository root) prints the counts and
the first traceback examples.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import math
import multiprocessing as mp
import random
import resource
import shutil
import tempfile
import time
import tomllib
import traceback
from collections import Counter
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from bench.resources import protocols_dir, rigs_dir

HANG_S = 10.0
MEMORY_LIMIT_BYTES = 4 << 30  # per worker: a runaway allocation is a MemoryError (a traceback), not a dead machine
CLASSES = ("refused", "accepted", "traceback", "hang")


class Raw:
    """TOML text written verbatim by :func:`to_toml` (for nesting deeper than a recursive writer allows)."""

    def __init__(self, text: str) -> None:
        self.text = text


def _value(v: Any) -> str:
    if isinstance(v, Raw):
        return v.text
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a TOML basic string (lone surrogates make invalid TOML: fine)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__}")


def to_toml(data: dict[str, Any]) -> str:
    """``data`` as TOML: one ``key = value`` line per top-level key, inline tables and arrays below."""
    return "".join(f"{json.dumps(str(k))} = {_value(v)}\n" for k, v in data.items())


def _deep_array(depth: int) -> Raw:
    return Raw("[" * depth + "1" + "]" * depth)


def _nested_repeats(depth: int, count: int) -> dict[str, Any]:
    step: dict[str, Any] = {"type": "hold", "duration_s": 0.1}
    for _ in range(depth):
        step = {"type": "repeat", "count": count, "steps": [step]}
    return step


def _huge_sweep(rng: random.Random) -> dict[str, Any]:
    inner = [{"type": "hold", "duration_s": 0.1}]
    if rng.random() < 0.1:  # the most steps a file may expand to: seconds to validate each, so rarer
        return rng.choice([
            {"type": "repeat", "count": rng.choice([5_000, 100_000]), "steps": [{"type": "hold", "duration_s": 0.001}]},
            {"type": "sweep", "over": {"v": {"start": "0 V", "stop": "1 kV", "num": 100_000}},
             "steps": [{"type": "ramp", "to": "{v}", "duration_s": 0.001}]}])
    return rng.choice([
        {"type": "sweep", "over": {"v": {"start": "0 V", "stop": "1 kV", "num": rng.choice([10**6, 10**9, 2**62])}},
         "steps": inner},
        {"type": "sweep", "over": {"v": {"start": 0, "stop": 1e12, "step": 1e-3}}, "steps": inner},
        {"type": "sweep", "over": {"a": list(range(1000)), "b": list(range(1000))}, "steps": inner},
        {"type": "sweep", "over": {"v": {"start": 0, "stop": 1, "num": float("inf")}}, "steps": inner},
        {"type": "sweep", "over": {"voltage": "7 kV"}, "steps": inner},
        {"type": "repeat", "count": rng.choice([10**6, 10**12, 2**63 - 1]), "steps": inner},
        {"type": "repeat", "count": 10**6, "steps": []},

        _nested_repeats(rng.choice([5, 10, 21, 40]), rng.choice([1, 2, 10, 100])),
        {"type": "hold", "duration_s": rng.choice([3600.0 * 3, 1e6, 6e5, 1e300])},
        {"type": "waveform", "amplitude": "1 kV", "frequency_Hz": 1000, "cycles": rng.choice([1e6, 1e9, 1e300])},
    ])


def _weird(rng: random.Random) -> Any:
    return rng.choice([
        float("nan"), float("inf"), float("-inf"), -1, 0, 0.0, -1e-300, 1e300, 2**63 - 1, -(2**63), 10**30, 1e-320,
        "", "abc", "7 kV", "1e999 V", "nan V", "-inf mm", "0 m/s", "1e300 kV", "{x}", "\u0000", "é" * 50,
        True, [], [1, 2], ["5 kV", "6 kV"], {}, {"a": 1}, {"start": 0, "stop": 1, "num": 3},
        _deep_array(rng.choice([30, 70, 1500])),
    ])


def _paths(obj: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path into a parsed TOML document (tables and arrays)."""
    out: list[tuple[Any, ...]] = []
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    for k, v in items:
        out.append((*prefix, k))
        out += _paths(v, (*prefix, k))
    return out


def _parent(doc: Any, path: tuple[Any, ...]) -> Any:
    for k in path[:-1]:
        doc = doc[k]
    return doc


def _mutate_tree(doc: dict[str, Any], rng: random.Random) -> str:
    """Mutate ``doc`` in place once; return a description."""
    paths = _paths(doc)
    if not paths:
        doc["x"] = _weird(rng)
        return "add x"
    path = rng.choice(paths)
    parent, key = _parent(doc, path), path[-1]
    where = ".".join(str(k) for k in path)
    op = rng.random()
    value = parent[key]
    if op < 0.15 and isinstance(value, int | float) and not isinstance(value, bool):
        parent[key] = type(value)(value * rng.choice([0, 0.5, 0.9, 1.1, 2, 10]))
        return f"{where} = {parent[key]!r} (scaled)"
    if op < 0.55:
        new = _weird(rng)
        parent[key] = new
        return f"{where} = {_value(new)[:40]}"
    if op < 0.65:
        del parent[key]
        return f"delete {where}"
    if op < 0.75:
        if isinstance(parent, list):
            parent.insert(int(key), copy.deepcopy(parent[key]))
            return f"duplicate {where}"
        parent[f"{key}_extra"] = parent[key]
        return f"unknown key {where}_extra"
    steps = doc.get("steps")
    if isinstance(steps, list):
        new_step = _huge_sweep(rng)
        steps.insert(rng.randrange(len(steps) + 1), new_step)
        return f"insert step {_value(new_step)[:60]}"
    parent[key] = _deep_array(rng.choice([30, 1500]))
    return f"{where} = deep array"


def _mutate_text(text: str, rng: random.Random) -> tuple[bytes, str]:
    """A text-level mutation of a TOML file (truncation, random bytes, duplicated tables, deep nesting)."""
    data = text.encode()
    op = rng.randrange(4)
    if op == 0:
        cut = rng.randrange(len(data) + 1)
        return data[:cut], f"truncated at byte {cut}"
    if op == 1:
        b = bytearray(data)
        for _ in range(rng.randint(1, 8)):
            b[rng.randrange(len(b))] = rng.randrange(256)
        return bytes(b), "random bytes"
    if op == 2:
        headers = [ln for ln in text.splitlines() if ln.startswith("[") and not ln.startswith("[[")]
        if headers:
            h = rng.choice(headers)
            return (text + f"\n{h}\n").encode(), f"duplicate table {h}"
        return (text + "\n[x]\n[x]\n").encode(), "duplicate table [x]"
    depth = rng.choice([25, 100, 1500, 5000])
    return (text + "\nz = " + "[" * depth + "]" * depth + "\n").encode(), f"array nested {depth} deep"


@dataclass
class Case:
    """One fuzzed file and how it is validated: ``bench validate <protocol> [--rig <rig>]``."""

    label: str
    protocol: Path
    rig: Path | None
    mutation: str
    file: Path  # the mutated file (the protocol or the rig)


@dataclass
class Outcome:
    """Classification of one case."""

    case: Case
    kind: str
    detail: str = ""
    seconds: float = 0.0


@dataclass
class Report:
    """Counts over a fuzz run."""

    outcomes: list[Outcome] = field(default_factory=list)

    @property
    def counts(self) -> Counter[str]:
        """files and the count of each class."""
        c = Counter(o.kind for o in self.outcomes)
        return Counter({"files": len(self.outcomes), **{k: c.get(k, 0) for k in CLASSES}})

    def examples(self, kind: str, n: int = 5) -> list[Outcome]:
        """The first ``n`` outcomes of a class."""
        return [o for o in self.outcomes if o.kind == kind][:n]


def seed_files(kind: str) -> list[Path]:
    """Shipped files the mutants derive from."""
    if kind == "protocols":
        return sorted((protocols_dir() / "short").glob("*.toml"))
    return sorted(rigs_dir().glob("*.toml"))


def _protocol_for_rig(rig: Path) -> Path:
    """A short shipped protocol written for ``rig`` (or for its kind of specimen)."""
    data = tomllib.loads(rig.read_text())
    kind = data.get("specimen", {}).get("kind", "membrane")
    config = data.get("specimen", {}).get("lsdea", {}).get("configuration", "motor")
    name = {"membrane": "thesis-identification-short", "hung": "lsdea-isotonic-short",
            "blocked": "lsdea-isometric-short"}.get(kind if kind == "membrane" else config, "lsdea-isopotential-short")
    return protocols_dir() / "short" / f"{name}.toml"


def make_cases(n_protocols: int, n_rigs: int, seed: int, folder: Path) -> list[Case]:
    """Write ``n_protocols`` mutated protocol files and ``n_rigs`` mutated rig files into ``folder``."""
    rng = random.Random(seed)
    rigs = seed_files("rigs")
    cases: list[Case] = []
    for kind, n in (("protocols", n_protocols), ("rigs", n_rigs)):
        seeds = seed_files(kind)
        for i in range(n):
            src = rng.choice(seeds)
            text = src.read_text()
            doc = tomllib.loads(text)
            if kind == "protocols":  # the rig named relative to the shipped file: make it absolute
                header = doc.get("protocol", {})
                header["rig"] = str((src.parent / header.get("rig", "")).resolve())
                if rng.random() < 0.1:
                    header["rig"] = str(rng.choice(rigs))
            if rng.random() < 0.75:
                what = "; ".join(_mutate_tree(doc, rng) for _ in range(rng.choice([1, 1, 1, 2, 3])))
                body = to_toml(doc).encode()
            else:
                body, what = _mutate_text(to_toml(doc) if kind == "protocols" else text, rng)
            out = folder / f"{kind[:-1]}-{i:05d}.toml"
            out.write_bytes(body)
            if kind == "protocols":
                cases.append(Case(f"{src.name}: {what}", out, None, what, out))
            else:
                cases.append(Case(f"{src.name}: {what}", _protocol_for_rig(src), out, what, out))
    return cases


def classify(case: Case) -> tuple[str, str]:
    """Validate one case as ``bench validate`` does; (class, detail). Runs in the worker."""
    from bench.runtime.run import plan_run
    from drivers.errors import InstrumentError

    try:
        plan_run(case.protocol, case.rig, False)
    except (ValueError, OSError, InstrumentError) as exc:  # what the CLI turns into one line, exit 2
        msg = str(exc)
        names_a_file = msg.startswith(("protocol file ", "rig file "))  # the file at fault, then the field
        if "\n" in msg or not names_a_file or len(msg) > 1000:
            return "traceback", f"unclear refusal ({type(exc).__name__}): {msg[:300]!r}"
        return "refused", msg
    except BaseException as exc:  # anything else is what the fuzzer looks for
        tb = traceback.format_exception(exc)
        return "traceback", "".join(tb[-3:])[-1500:]
    return "accepted", ""


def _worker(conn: Connection) -> None:
    import bench.protocol.predict as dry

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))
    # the dry run's budget grows with the run (2 % of it, up to 30 min): a valid multi-hour mutant (a 3-h hold,
    # 100,000 steps of 0.1 s) would dry-run for minutes, bounded and no hang, but over the time limit here; the
    # worker holds every dry run to the budget's 30-s floor, as the fuzzer has always had it
    dry.DRY_RUN_CEILING_S = dry.DRY_RUN_BUDGET_S
    while True:
        case = conn.recv()
        if case is None:
            return
        conn.send(classify(case))


class _Worker:
    """A forked worker process fed one case at a time; killed (and replaced) when a case runs over."""

    def __init__(self, ctx: Any) -> None:
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker, args=(child,), daemon=True)
        self.proc.start()
        child.close()

    def run(self, case: Case, limit: float) -> tuple[str, str]:
        self.conn.send(case)
        if self.conn.poll(limit):
            try:
                return self.conn.recv()
            except EOFError:
                pass
            return "traceback", f"worker died (exit code {self.proc.exitcode})"
        self.kill()
        return "hang", f"still running after {limit:g} s"

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join()
        self.conn.close()

    def stop(self) -> None:
        with contextlib.suppress(OSError):
            self.conn.send(None)
        self.proc.join(5)
        self.kill()


def warm_up() -> None:
    """Import and JIT-compile what validation uses, once, so that every forked worker starts warm (a numba
    compile in a worker would otherwise count against its time limit)."""
    from bench.protocol.predict import predict
    from bench.protocol.program import compile_program
    from bench.protocol.schema import load_protocol
    from bench.runtime.run import resolve_rig

    for path in seed_files("protocols"):
        with contextlib.suppress(Exception):
            protocol = load_protocol(path)
            predict(compile_program(protocol, resolve_rig(protocol)))


def run_fuzz(n_protocols: int, n_rigs: int, seed: int, limit: float = HANG_S, keep: Path | None = None,
             progress: bool = False) -> Report:
    """Generate the mutants, validate each in a worker with a hard time limit, and classify them."""
    warm_up()
    ctx = mp.get_context("fork")
    folder = Path(tempfile.mkdtemp(prefix="bench-fuzz-"))
    report = Report()
    worker: _Worker | None = None
    try:
        cases = make_cases(n_protocols, n_rigs, seed, folder)
        for i, case in enumerate(cases):
            if worker is None:
                worker = _Worker(ctx)
            t0 = time.monotonic()
            kind, detail = worker.run(case, limit)
            if kind == "hang" or not worker.proc.is_alive():
                worker.kill()
                worker = None
            report.outcomes.append(Outcome(case, kind, detail, time.monotonic() - t0))
            if keep is not None and kind in ("traceback", "hang"):
                keep.mkdir(parents=True, exist_ok=True)
                shutil.copy(case.file, keep / case.file.name)
            if progress and (i + 1) % 500 == 0:
                print(f"  {i + 1} files: {dict(report.counts)}", flush=True)
    finally:
        if worker is not None:
            worker.stop()
        shutil.rmtree(folder, ignore_errors=True)
    return report


def main(argv: list[str] | None = None) -> int:
    """``python -m tests.fuzzing.files``: print the counts and the first traceback and hang examples."""
    ap = argparse.ArgumentParser(prog="python -m tests.fuzzing.files", description=__doc__.splitlines()[0])
    ap.add_argument("--protocols", type=int, default=200, help="mutated protocol files")
    ap.add_argument("--rigs", type=int, default=200, help="mutated rig files")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--limit", type=float, default=HANG_S, help="seconds per file before it counts as a hang")
    ap.add_argument("--keep", type=Path, help="copy the files that gave a traceback or hung here")
    ap.add_argument("--examples", type=int, default=5)
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    report = run_fuzz(args.protocols, args.rigs, args.seed, args.limit, args.keep, progress=True)
    c = report.counts
    print(f"files {c['files']}, refused {c['refused']}, accepted {c['accepted']}, tracebacks {c['traceback']}, "
          f"hangs {c['hang']} ({time.monotonic() - t0:.0f} s, seed {args.seed})")
    slowest = max(report.outcomes, key=lambda o: o.seconds, default=None)
    if slowest is not None:
        print(f"slowest file: {slowest.seconds:.2f} s ({slowest.case.label[:120]}; {slowest.kind})")
    for kind in ("traceback", "hang"):
        for o in report.examples(kind, args.examples):
            print(f"--- {kind}: {o.case.label[:200]}\n{o.detail.rstrip()}")
    return 1 if c["traceback"] or c["hang"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
