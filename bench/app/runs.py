"""Use cases on runs: plan one (or the rest of a campaign), execute it, inspect run files."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from bench.rig import RigConfig
    from bench.runtime.engine import Engine, OperatorFn, RunResult
    from bench.runtime.run import Plan, Resume
    from bench.storage.chunks import StreamChunks
    from bench.storage.runfile import RunFile


@dataclass
class PreparedRun:
    """A run planned and ready to execute: the plan, where it writes, what it records as metadata; for a resumed
    campaign, the link to the earlier file and the interlock reset that made it possible."""

    plan: Plan
    path: Path  # the run file it will write
    metadata: dict[str, str]
    link: Resume | None = None
    reset: tuple[str, str] | None = None  # (who, why) when resuming resets a latched interlock (once connected)
    claimed: bool = False  # its file's name is claimed: its log made (:func:`claim_output`)

    @property
    def needs_operator(self) -> bool:
        """Whether someone must confirm specimen changes (a real rig; the simulated one applies them itself)."""
        return any(s.changes for s in self.plan.program.segments) and not self.plan.rig.simulated


def login_name(operator: str | None) -> str:
    """Who acts: ``operator`` or the login name, checked as a label (``--operator`` named where it is refused: an
    empty one was taken as the login name by `bench pause`, refused by `bench run`)."""
    import getpass

    from bench.protocol.schema import MAX_OPERATOR, check_label

    if operator is not None:
        try:
            return check_label(operator, MAX_OPERATOR)
        except ValueError as exc:
            raise ValueError(f"--operator: {exc}") from None
    return check_label(getpass.getuser(), MAX_OPERATOR)


def reason_given(why: str | None, needed: str | None = None) -> str:
    """``--why`` checked as a note is (one line of printable text, at most ``MAX_NOTE`` characters: an outside
    tester's bell character went into a run's events as it was); empty: '' or, where a reason is ``needed`` (what
    it must say), refused in one line."""
    from bench.protocol.schema import MAX_NOTE, check_label

    if not why or not why.strip():
        if needed is not None:
            raise ValueError(f"--why: {needed}")
        return ""
    try:
        return check_label(why, MAX_NOTE)
    except ValueError as exc:
        raise ValueError(f"--why: {exc}") from None


def plan_protocol(protocol_file: Path, rig: Path | None = None, sim: bool = False,
                  progress: Callable[[float], None] | None = None) -> Plan:
    """Load, compile, check the link budget and dry-run a protocol on its rig (or ``rig``)."""
    from bench.runtime.run import plan_run

    protocol_file = shipped_protocol_file(protocol_file)
    if not protocol_file.exists():
        raise ValueError(f"protocol file {protocol_file}: not found{protocol_suggestion(protocol_file)}")
    rig = rig_file(rig)
    if rig is not None and sim is False and not rig.exists():
        from bench.protocol.schema import missing_rig_ref

        hint = rig_suggestion(rig)  # the file meant, else the closest rig names
        raise ValueError(f"rig file {rig}: not found{hint}" if hint else
                         missing_rig_ref(Path.cwd(), str(rig), "--rig takes a rig file or a shipped rig's name"))
    return plan_run(protocol_file, rig, sim, progress)


def shipped_protocol_file(protocol: Path) -> Path:
    """A protocol file, or — no such file, no such file with ``.toml`` either — the shipped protocol of that name
    (``bench run thesis-identification``, the names ``bench protocols list`` shows: "not found" before; an outside
    tester). A name of none is left as given: its error says "not found", with the shipped name meant if one is
    close."""
    if protocol.exists():
        return protocol
    if protocol.with_name(protocol.name + ".toml").is_file():
        return protocol.with_name(protocol.name + ".toml")
    from bench.resources import protocol as shipped

    try:
        found = shipped(str(protocol))
    except ValueError:
        return protocol
    name = protocol.name.removesuffix(".toml")
    own = [d / "protocols" / (name + ".toml") for d in (protocol.parent, protocol.parent / "..")]
    if any(p.is_file() and p.resolve() != found.resolve() for p in own):  # a lab folder's own (maybe edited) copy
        return protocol  # of that name: never passed over silently for the shipped one (a reviewer); refused, named
    return found  # (the repository's protocols/ is the shipped one itself)


def protocol_suggestion(protocol: Path) -> str:
    """For a protocol file that is not there: "; did you mean protocols/NAME.toml?" (a lab folder's own copy), else
    "; did you mean the shipped protocol X?" where a shipped name is close ("" otherwise)."""
    import difflib

    from bench.resources import shipped_protocols

    name = protocol.name.removesuffix(".toml")
    own = next((p for p in (protocol.parent / "protocols" / (name + ".toml"),
                            protocol.parent / ".." / "protocols" / (name + ".toml")) if p.is_file()), None)
    if own is not None:
        return f"; did you mean {os.path.normpath(own)} (this lab folder's copy)?"

    names = shipped_protocols()
    close = difflib.get_close_matches(protocol.name.removesuffix(".toml"), [n.rsplit("/", 1)[-1] for n in names],
                                      n=1, cutoff=0.75)
    return f"; did you mean the shipped protocol {close[0]}?" if close else ""


def rig_file(rig: Path | None) -> Path | None:
    """``--rig``: a rig file, or — no such file, a bare name — the shipped rig of that name (as a protocol's ``rig``
    may name one: ``--rig thesis-sim`` was refused with a hint into site-packages; an outside tester). Where a file
    of that name with ``.toml``, or ``rigs/NAME.toml``, is here (a lab folder's own copy), nothing is chosen: the
    refusal suggests it (:func:`rig_suggestion`)."""
    from bench.protocol.schema import resolve_rig_ref

    if rig is None or rig.exists():
        return rig
    name = rig.name.removesuffix(".toml")
    if any(p.is_file() for p in (rig.with_name(name + ".toml"), rig.parent / "rigs" / (name + ".toml"),
                                 rig.parent / ".." / "rigs" / (name + ".toml"))):  # (from a lab's protocols/)
        return rig
    return resolve_rig_ref(Path.cwd(), str(rig))


def rig_suggestion(rig: Path) -> str:
    """For a ``--rig`` that names no file: "; did you mean X?" where X is the rig file it probably meant — the
    name with ``.toml``, ``rigs/NAME.toml`` here (a lab folder, the repository), else the shipped rig of that name
    (``--rig thesis-sim``: a rig's name where its file is asked for); "" when none exists."""
    from bench.resources import shipped_rigs

    name = rig.name.removesuffix(".toml")
    here = [rig.with_name(name + ".toml"), rig.parent / "rigs" / (name + ".toml"),
            rig.parent / ".." / "rigs" / (name + ".toml")]
    found = next((p for p in here if p.is_file()), None) or shipped_rigs().get(name)
    return f"; did you mean {found}?" if found is not None else ""


def _refuse_other_specimen(resume: Path, specimen_id: str | None) -> None:
    """ValueError (one line, nothing touched) for a ``--specimen-id`` that is not the one of the campaign ``resume``
    continues: the resumed file carried the new ID and the campaign went on under it, its history split over two
    specimens, with no word (outside tester). A resume continues the same specimen; a new one is a new run."""
    from bench.storage.runfile import open_run

    if specimen_id is None or not specimen_id.strip():
        return
    try:
        was = str(open_run(resume, streams=False).attrs.get("specimen_id", "") or "")
    except (OSError, ValueError):  # a file the resume must recover or refuse first: its own checks say so
        return
    if was and was != specimen_id:
        raise ValueError(f"--specimen-id {specimen_id}: {resume} is a campaign on specimen {was}, and a resume "
                         f"continues it on that specimen (leave --specimen-id out; a new specimen starts a new run)")


def prepare_run(protocol_file: Path | None, *, rig: Path | None = None, sim: bool = False, out: Path = Path("runs"),
                resume: Path | None = None, operator: str | None = None, specimen_id: str | None = None,
                notes: list[str] | None = None, why: str | None = None, dry_run: bool = False,
                on_recovered: Callable[[str], None] | None = None,
                progress: Callable[[float], None] | None = None) -> PreparedRun:
    """Plan a run of ``protocol_file``, or with ``resume`` the rest of that file's campaign (recovered first if a
    crash left it open: each line of what was done goes to ``on_recovered``); on a latched rig a resume needs
    ``why``, and the run resets the latch once the rig has connected (not on a ``dry_run``). ValueError (one line)
    for what cannot run."""
    from bench.runtime.run import default_output, run_metadata

    link = None
    reset = None
    if resume is not None:
        from bench.protocol.schema import load_protocol
        from bench.runtime.run import plan_resume
        from bench.storage.runfile import open_run

        if out != Path("runs") and out.resolve() != resume.resolve().parent:  # before anything is done to the file
            raise ValueError(f"--out {out}: a resumed campaign is written beside its latest file, in "
                             f"{resume.parent} (a second resume looks for a continuation there; elsewhere it would "
                             "fork the campaign)")
        if not (why and why.strip()) and rig is None and not sim:  # before a crashed file is recovered: refused
            _refuse_latched_before_recovery(resume)  # (a latch needs --why) with nothing touched
        _refuse_other_specimen(resume, specimen_id)
        plan, link, recovered = plan_resume(resume, rig_file(rig), sim, progress)
        if protocol_file is not None:
            protocol_file = shipped_protocol_file(protocol_file)
        if protocol_file is not None and load_protocol(protocol_file).sha256 != plan.protocol.sha256:
            raise ValueError(f"protocol file {protocol_file}: not the protocol of {resume} (its text differs); "
                             "--resume needs no protocol file")
        for line in recovered:
            if on_recovered is not None:
                on_recovered(line)
        old = {k: v for k, v in open_run(resume, streams=False).attrs.items() if isinstance(v, str)}
        metadata = run_metadata(plan.protocol, operator or old.get("operator"), specimen_id or old.get("specimen_id"),
                                notes)
        if not dry_run:  # an instrument another process holds refuses the resume before the latch is reset
            from bench.runtime.rig_lock import claimed

            with claimed(plan.rig):
                pass
        reset = _reset_for_resume(plan.rig, operator or old.get("operator"), why, dry_run, metadata, link)
        link.reset = reset  # done by the run once the rig has connected: a start that fails keeps the latch
        out = resume.parent
    elif protocol_file is None:
        raise ValueError("give a protocol file, or --resume RUN.h5 to continue a campaign")
    else:
        plan = plan_protocol(protocol_file, rig, sim, progress)
        metadata = run_metadata(plan.protocol, operator, specimen_id, notes)
        if not dry_run:  # refused before the plan is shown and the run's log made (execute checks again)
            from bench.runtime.latch import drive_of, refuse_if_latched

            refuse_if_latched(plan.rig.name, drive_of(plan.rig))
    return PreparedRun(plan, default_output(plan, out), metadata, link, reset)


def _refuse_latched_before_recovery(resume: Path) -> None:
    """A resume without ``--why`` of a campaign whose stored rig is latched: refused before its file is recovered
    (a tester: the refusal came after "recovered: … marked it recovered", a refused command that changed the file).
    By the stored rig's name and drive; the plan's own check (:func:`_reset_for_resume`) follows for the rest."""
    from bench.rig import rig_from_toml
    from bench.runtime.latch import drive_of, holding
    from bench.storage.runfile import open_run

    try:
        stored = rig_from_toml(str(open_run(resume, streams=False).attrs["rig_toml"]))
    except (OSError, ValueError, KeyError):  # the plan says what is wrong with the file
        return
    found = holding(stored.name, drive_of(stored))
    if found:
        raise ValueError(f"rig {stored.name}: interlock latched ({found[0].get('fault')}): --why '…' resets it to "
                         "resume")


def _reset_for_resume(rig: RigConfig, operator: str | None, why: str | None, dry_run: bool,
                      metadata: dict[str, str], link: Resume) -> tuple[str, str] | None:
    """A resumed campaign on a latched rig (or on a real rig's amplifier drive latched under another name): the
    operator's reset (who and why), recorded in the new file's ``metadata``. The reset itself is the run's, once the
    rig has connected (:func:`~bench.runtime.run.execute`): a resume that fails to start leaves the latch, and it
    resets only the latches seen here (``link.reset_seen``): one that appears later refuses the run."""
    from bench.runtime.latch import drive_of, holding, latch_key

    drive = drive_of(rig)
    found = holding(rig.name, drive)
    if not found:
        return None
    was = found[0]
    link.reset_seen = frozenset(latch_key(w) for w in found)
    if not why or not why.strip():
        raise ValueError(f"rig {rig.name}: interlock latched ({was.get('fault')}): --why '…' resets it to resume")
    why = reason_given(why)
    if dry_run:
        return None
    who = login_name(operator)
    metadata["interlock_reset"] = f"by {who}: {why} (latched at {was.get('at')}: {was.get('fault')})"
    return who, why


def check_executable(prepared: PreparedRun, *, virtual_time: bool, can_confirm: bool) -> None:
    """Refuse, in one line, a run that cannot go: virtual time on a real rig, or specimen changes that nobody can
    confirm (no terminal and no ``--yes``)."""
    plan = prepared.plan
    if virtual_time and not plan.rig.simulated:
        raise ValueError(f"rig {plan.rig.name} is real: --virtual-time needs a simulated rig (add --sim)")
    if prepared.needs_operator and not can_confirm:
        raise ValueError("this protocol changes the specimen between tests: run it interactively or pass --yes")


def claim_output(prepared: PreparedRun) -> None:
    """Claim the run's file before its log is written (:func:`~bench.runtime.run.reserve_output`): the planned name,
    or the next free one when another run took it since. Whole or not at all: a stop signal within it is held until
    it ends, the claim then taken back and the signal's own handler called — a signal there left an empty log,
    though the line said no log was written (a reviewer)."""
    import signal
    import threading

    from bench.runtime.engine import STOP_SIGNALS
    from bench.runtime.run import reserve_output

    held: list[int] = []
    saved: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():  # (handlers run in the main thread only)
        for sig in STOP_SIGNALS:
            if signal.getsignal(sig) is not None:  # (a handler set outside Python cannot be put back: left as is)
                saved[int(sig)] = signal.signal(sig, lambda s, _f: held.append(s))
    try:
        claimed = reserve_output(prepared.path)
    finally:
        for number, handler in saved.items():
            signal.signal(number, handler)
    log = claimed.with_suffix(".log")  # made empty just now, by this claim
    for number in held:  # in order; one its handler ignores passes on to the next
        handler = saved[number]
        if callable(handler):
            try:
                handler(number, None)  # raises, as a stop before the run does
            except BaseException:
                log.unlink(missing_ok=True)
                raise
        elif handler == signal.SIG_DFL:
            log.unlink(missing_ok=True)
            os.kill(os.getpid(), number)  # the default action: the process ends
    prepared.path = claimed
    prepared.claimed = True


def release_claim(prepared: PreparedRun) -> None:
    """Take back the claim of a run that never started (a stop signal as the claim ended): its log, still empty."""
    log = prepared.path.with_suffix(".log")
    if prepared.claimed and log.is_file() and log.stat().st_size == 0:
        log.unlink(missing_ok=True)
        prepared.claimed = False


def execute_run(prepared: PreparedRun, *, virtual_time: bool = False, operator: OperatorFn | None = None,
                allow_no_watchdog: bool = False, catalog: str | None = None,
                on_engine: Callable[[Engine, object], None] | None = None) -> RunResult:
    """Execute a prepared run into its file; ``on_engine`` gets the engine once built (a live view, pause keys);
    ``catalog`` is the run catalogue's URL (default: $BENCH_CATALOG, else beside the runs)."""
    from bench.runtime.run import execute

    if catalog:  # what the run's catalogue hooks read (bench/storage/catalog.py)
        os.environ["BENCH_CATALOG"] = catalog
    kwargs: dict[str, Any] = {"on_engine": on_engine} if on_engine is not None else {}
    return execute(prepared.plan, prepared.path, virtual=virtual_time, operator=operator,
                   allow_no_watchdog=allow_no_watchdog, metadata=prepared.metadata, resume=prepared.link, **kwargs)


@dataclass
class StreamSummary:
    """What ``bench inspect`` shows of a stream: its records, first and last time, units, last value of each
    column — read as single records, never the stream whole."""

    samples: int
    first: float | None
    last_t: float | None
    units: dict[str, str]
    last: dict[str, Any]  # column → its last value (None when the stream is empty)


def summarise(streams: StreamChunks) -> dict[str, StreamSummary]:
    """Each stream of an open run file summarised from its first and last records."""
    out = {}
    for name, n in streams.length.items():
        cols = streams.columns[name][1:]
        first = float(streams.read(name, "t", 0, 1)[0]) if n else None
        last_t = float(streams.read(name, "t", n - 1, n)[0]) if n else None
        last = {c: (streams.read(name, c, n - 1, n)[0] if n else None) for c in cols}
        units = streams.units(name)
        out[name] = StreamSummary(n, first, last_t, {k: units[k] for k in streams.f[name]}, last)  # file order
    return out


@dataclass
class Inspection:
    """What a run file holds (``bench inspect``): the file read (events, state; its streams summarised), its
    attributes and notes, the fits stored with it, and its campaign."""

    file: Path
    run: RunFile
    streams: dict[str, StreamSummary]
    notes: list[str]
    fits: list[dict[str, Any]]
    fits_error: str  # a fit file of another run beside it: said, the run itself still shown
    campaign: list[dict[str, object]] | str  # the chain of linked files (an error text when a link is broken)
    campaign_text: tuple[str, bool] | None = None  # the chain described (text, whether it is an error), if resumed
    continued_in: Path | None = None  # the file that continued this one's campaign (bench run --resume), if any
    manual: bool = field(init=False)

    def __post_init__(self) -> None:
        self.manual = bool(self.run.attrs.get("session_log"))  # a manual-control session's readings

    @property
    def stream_ends(self) -> list[float]:
        """The time of each stream's last sample [s] (streams without samples left out): a stream's whole-chunk
        writes run ahead of ``recorded up to`` (``/status/updated``, the time to which every stream is complete)."""
        return [s.last_t for s in self.streams.values() if s.samples and s.last_t is not None]

    @property
    def last_sample(self) -> float | None:
        """The time of the last sample of any stream [s] (None: no samples)."""
        return max(self.stream_ends, default=None)

    @property
    def complete(self) -> bool:
        return bool(self.run.complete)

    KEYS = ("protocol_name", "protocol_path", "protocol_sha256", "rig_name", "simulated", "clock", "wire_time",
            "software", "start_time", "duration_planned", "operator", "specimen_id", "session_log")

    def record(self) -> dict[str, object]:
        """The inspection as plain data (``bench inspect --json``)."""
        r, a = self.run, self.run.attrs
        return {"file": str(self.file), **{k: a.get(k) for k in self.KEYS}, "notes": self.notes,
                "fits": [{"file": f["file"], "group": f["group"], "model": f.get("model"), "rms": f.get("rms"),
                          "created": f.get("created"), "records": f.get("records"),
                          "parameters": dict(zip(f["names"], f["values"], strict=True))} for f in self.fits],
                "fits_error": self.fits_error or None,
                "state": r.state, "complete": r.complete,
                "incomplete_reason": None if r.complete else r.incomplete_reason, "reason": r.reason,
                "end_time": r.end_time, "recorded_up_to_s": r.updated, "last_sample_s": self.last_sample,
                "paused_s": r.paused_s, "state_shown": r.state_shown,
                "streams": {name: {"samples": s.samples, "from_s": s.first, "to_s": s.last_t, "units": s.units,
                                   "last": s.last} for name, s in self.streams.items()},
                "events": [{"t_s": t, "step": step, "kind": kind, "text": text}
                           for t, step, kind, text in r.event_list()],
                "campaign": self.campaign, "recovered_at": r.recovered_at or None,
                "continued_in": None if self.continued_in is None else str(self.continued_in)}


def inspect_run(run_file: Path) -> Inspection:
    """Read a run file (finished or being written) with its fits and campaign."""
    from bench.identify.store import read_fits
    from bench.storage.chain import campaign as campaign_of
    from bench.storage.chain import describe
    from bench.storage.chunks import open_source

    with open_source(run_file) as src:
        r, streams = src.run, summarise(src.streams)
    a = r.attrs
    notes = [n for n in str(a.get("notes", "")).split("\n") if n]
    try:
        fits, fits_error = read_fits(run_file), ""
    except (ValueError, OSError) as exc:  # a fit file of another run beside it: the run itself is still shown
        fits, fits_error = [], " ".join(str(exc).splitlines())
    described, later = None, None
    try:
        links = campaign_of(run_file)  # also the files that continued it: the first file shows the whole campaign
    except ValueError as exc:
        campaign: list[dict[str, object]] | str = str(exc)
        if a.get("previous_file"):
            described = (str(exc), True)
    else:
        campaign = [{"file": str(ln.path), "state": ln.state, "complete": ln.complete,
                     "resumed_at_step": ln.resumed_at_step}
                    for ln in links] if len(links) > 1 or a.get("previous_file") else []
        mine = next(k for k, ln in enumerate(links) if ln.path.resolve() == run_file.resolve())
        later = links[mine + 1].path if mine + 1 < len(links) else None
        if len(links) > 1:
            described = (describe(links), False)
    return Inspection(run_file, r, streams, notes, fits, fits_error, campaign, described, later)
