"""Campaigns of linked run files: a run resumed with ``bench run --resume`` writes a new file whose
``previous_file`` attribute names the one it continues (relative to its own folder) and whose ``campaign_id`` is
the first file's ``run_id``. Analysis, reports and fits take the whole chain as one campaign: each step from the
file in which it completed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from bench.storage.absent import absent_run_file
from bench.storage.runfile import open_run

MAX_CHAIN = 1000  # a longer chain is a loop or a damaged attribute


@dataclass(frozen=True)
class Link:
    """One file of a campaign chain: its path, state, the step it resumed at (None: the first file)."""

    path: Path
    state: str
    complete: bool
    resumed_at_step: int | None  # the step's index in the program (0-based, as the file's events number steps)
    steps: int = 0  # the program's steps
    run_id: str = ""  # the file's run_id: a copy of a file has its original's
    shown: str = ""  # its state as listings show it (a dead writer's "running": "crashed or killed")


def chain(path: str | Path) -> list[Link]:
    """The files of the campaign ``path`` belongs to, up to ``path``, first one first (following
    ``previous_file``). ValueError (one line naming the file) when a linked file is missing or the links loop."""
    out: list[Link] = []
    p: Path | None = Path(path)
    seen: set[Path] = set()
    while p is not None:
        key = p.resolve()
        if key in seen or len(out) >= MAX_CHAIN:
            raise ValueError(f"run file {path}: its previous_file links loop back to {p}")
        seen.add(key)
        if not p.is_file():
            if not out:
                raise ValueError(absent_run_file(Path(path)))
            raise ValueError(f"run file {out[-1].path}: the file it continues, {p}, is missing "
                             "(keep a campaign's files together)")
        run = open_run(p, streams=False)
        step = run.attrs.get("resumed_at_step")
        out.append(Link(p, run.state, run.complete, None if step is None else int(step), int(run.program.shape[0]),
                        str(run.attrs.get("run_id", "")), run.state_shown))
        prev = run.attrs.get("previous_file")
        p = (p.parent / str(prev)) if prev else None
    return out[::-1]


_INDEX: dict[Path, tuple[int, dict[str, Path]]] = {}  # folder → (its mtime, previous_run_id → the file naming it)


def _continuations(folder: Path, cached: bool) -> dict[str, Path]:
    """``previous_run_id`` → the (first, by name) run file of ``folder`` that names it. ``cached``: each file opened
    once per folder and process, again only after the folder changed (a file added or removed changes its mtime) —
    for reading a campaign; a resume's fork check reads the folder afresh (a continuation being created may not
    have its links written yet when the folder changes). Files that cannot be read as run files are passed over."""
    key = folder.resolve()
    stamp = key.stat().st_mtime_ns
    hit = _INDEX.get(key)
    if cached and hit is not None and hit[0] == stamp:
        return hit[1]
    index: dict[str, Path] = {}
    for other in sorted(folder.glob("*.h5")):
        try:  # as every reader opens a run: also one still being written, or a crashed writer's
            prev = str(open_run(other, streams=False).attrs.get("previous_run_id", ""))
        except (OSError, ValueError):  # not a run file, or one damaged beyond reading: not a continuation
            continue
        if prev:
            index.setdefault(prev, other)
    _INDEX[key] = (stamp, index)
    return index


def continued_in(path: str | Path, cached: bool = False) -> Path | None:
    """A file in ``path``'s folder that continues it (its ``previous_run_id`` is ``path``'s ``run_id``), or None.
    ``cached`` (reading a campaign): the folder's index kept from an earlier call (:func:`_continuations`), where a
    report of hundreds of files read the whole folder again for each stopped one."""
    p = Path(path)
    rid = str(open_run(p, streams=False).attrs.get("run_id", ""))
    later = _continuations(p.parent, cached).get(rid) if rid else None
    return None if later is None or later.resolve() == p.resolve() else later


def campaign(path: str | Path) -> list[Link]:
    """The whole campaign ``path`` belongs to, first file first: :func:`chain` up to ``path``, then the files that
    continued it, each found in its predecessor's folder (where ``bench run --resume`` writes it: a resume elsewhere
    is refused) by its ``previous_run_id``. The first file of a resumed campaign thus reads as the whole campaign,
    as its last does. ValueError as for :func:`chain`, or when the forward links loop."""
    out = chain(path)
    seen = {ln.path.resolve() for ln in out}
    # a completed file is never resumed (nothing is left): the folder is searched only after one that stopped
    while out[-1].state != "completed" and (later := continued_in(out[-1].path, cached=True)) is not None:
        if later.resolve() in seen or len(out) >= MAX_CHAIN:
            raise ValueError(f"run file {path}: the files continuing it loop back to {later}")
        seen.add(later.resolve())
        run = open_run(later, streams=False)
        step = run.attrs.get("resumed_at_step")
        out.append(Link(later, run.state, run.complete, None if step is None else int(step),
                        int(run.program.shape[0]), str(run.attrs.get("run_id", "")), run.state_shown))
    return out


def with_chains(paths: list[Path]) -> list[Path]:
    """``paths`` with the other files of each one's campaign (:func:`campaign`: the earlier ones and those that
    continued it), each file once, in campaign order.
    ValueError (one line naming both) for two files of one run (the same ``run_id``: a copy), whose record would
    count twice — a fit's intervals would narrow by √2 on no new data."""
    out: list[Path] = []
    seen: set[Path] = set()
    runs: dict[str, Path] = {}
    for p in paths:
        for link in campaign(p):
            key = link.path.resolve()
            if key in seen:
                continue
            if link.run_id and (first := runs.get(link.run_id)) is not None:
                raise ValueError(f"run files {first} and {link.path} are the same run (run_id {link.run_id}): a copy "
                                 "would count its record twice; give one of them")
            seen.add(key)
            runs[link.run_id] = link.path
            out.append(link.path)
    return out


def resumed_text(step: int, steps: int) -> str:
    """Where a campaign resumed, as the CLI says it (``bench run --resume``, ``inspect``, ``report``): counted from
    1 of the program's steps, with the 0-based index the file's ``resumed_at_step`` and events hold."""
    return f"step {step + 1} of {steps} (index {step})"


def describe(links: list[Link]) -> str:
    """One line: the campaign's files, how each ended and where each resumed."""
    parts = [f"{ln.path.name} ({ln.shown or ln.state}{'' if ln.complete else ', incomplete'}"
             + (f", resumed at {resumed_text(ln.resumed_at_step, ln.steps)}" if ln.resumed_at_step is not None
                else "") + ")"
             for ln in links]
    return " → ".join(parts)
