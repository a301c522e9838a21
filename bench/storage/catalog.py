"""The run catalogue: one row per run file, in SQLite beside the runs or on a shared PostgreSQL server.

The run files stay the source of truth; the catalogue is an index of them that can always be rebuilt
(:func:`rebuild`) and that is reconciled with the files before it is read (:func:`reconcile`): a row whose file
changed since the row was written (size, modification time, its fit file or report), a file without a row, and a
row without a file are fixed from the files. So a write the catalogue lost (a crash between a run's start and its
end, two benches writing at once, a server that was down) is never a wrong answer, only a late one.

Where: :func:`catalog_url` — ``--catalog URL``, else the ``BENCH_CATALOG`` environment variable, else
``sqlite:///<runs folder>/catalog.sqlite``. Any SQLAlchemy URL works; the tests run the same code on SQLite and on
a PostgreSQL server (``postgresql+psycopg://user@host/db``). Rows are keyed by host name and absolute path, so the
benches of a lab can share one server and each reconciles only its own folder.

What a row holds besides the file's metadata (per run, from the recorded data, for specimen histories):

* ``hv_time_s``: time with the measured amplifier voltage |V| above :data:`HV_THRESHOLD_V`, each sample weighted
  by the interval to the next one (a run's last sample counts 0);
* ``hv_cycles``: rises of the measured |V| above the threshold, re-armed when |V| falls below half of it (a
  unipolar pulse counts one, a bipolar sine period two: the Maxwell stress goes as V²);
* ``max_voltage_V`` and ``max_nominal_field_V_per_m`` = max |V| / the model's reference thickness (membrane
  ``L3``, LS-DEA ``t0``), with the model's breakdown field (membrane ``breakdown_field``, a true-field threshold;
  LS-DEA ``E0``, the unstretched film's) recorded beside it — both from the specimen stored in the run file. The
  nominal field is not compared with the breakdown field, a true-field limit: a specimen's history compares the
  true field E = Vλ²/L3 (physics.md §1.2), λ = λ_pre + u/L_d from the recorded laser at each voltage sample
  (:func:`peak_true_field`), read from the run files when the history is shown.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import socket
import threading
from collections.abc import Callable, Collection, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from bench.storage import hv_stats
from bench.storage.absent import absent_runs_folder
from bench.storage.hv_stats import HV_THRESHOLD_V, HvAccumulator, HvStats

if TYPE_CHECKING:
    import sqlalchemy as sa

    from bench.storage.recorder import Written

log = logging.getLogger("bench.storage.catalog")

ENV = "BENCH_CATALOG"
FILE_NAME = "catalog.sqlite"
SQLITE_BUSY_S = 60.0  # how long a SQLite writer waits for another bench's transaction
WAIT_NOTICE_S = 2.0  # a run's end row not written after this: a line says the CLI waits for the catalogue
PG_CONNECT_S = 5  # a shared server that does not answer: give up quickly (the run goes on)
PG_STATEMENT_S = 10  # a statement or lock wait on it (a locked table, a hung server) ends after this: the run goes on
PG_KEEPALIVE_S = 5  # a connection dropped mid-query is noticed within about 2 × this (TCP keepalives)

# columns compared when a test or a user asks whether two catalogues hold the same rows
COLUMNS = ("host", "path", "run_id", "campaign_id", "protocol_name", "protocol_sha256", "rig", "specimen_id",
           "operator", "notes", "state", "complete", "reason", "incomplete_reason", "start_time", "end_time",
           "steps_completed", "steps_total", "previous_file", "hv_time_s", "hv_cycles", "max_voltage_V",
           "max_nominal_field_V_per_m", "breakdown_field_V_per_m", "figures", "fits", "signature")


def catalog_url(folder: str | Path, given: str | None = None) -> str:
    """The catalogue to use for the runs in ``folder``: ``given``, else ``$BENCH_CATALOG``, else the SQLite file
    ``folder/catalog.sqlite``."""
    url = given or os.environ.get(ENV, "").strip()
    if url:
        return url
    return f"sqlite:///{Path(folder).resolve() / FILE_NAME}"


def _table(md: sa.MetaData) -> sa.Table:
    import sqlalchemy as sa

    text = sa.Text
    return sa.Table(
        "bench_runs", md,
        sa.Column("host", sa.String(255), primary_key=True),
        sa.Column("path", sa.String(2048), primary_key=True),
        sa.Column("run_id", sa.String(64)), sa.Column("campaign_id", sa.String(64)),
        sa.Column("protocol_name", sa.String(255)), sa.Column("protocol_sha256", sa.String(64)),
        sa.Column("rig", sa.String(255)), sa.Column("specimen_id", sa.String(255), index=True),
        sa.Column("operator", sa.String(255)), sa.Column("notes", text),
        sa.Column("state", sa.String(32)), sa.Column("complete", sa.Boolean), sa.Column("reason", text),
        sa.Column("incomplete_reason", text),
        sa.Column("start_time", sa.String(40), index=True), sa.Column("end_time", sa.String(40)),
        sa.Column("steps_completed", sa.Integer), sa.Column("steps_total", sa.Integer),
        sa.Column("previous_file", text),
        sa.Column("hv_time_s", sa.Float), sa.Column("hv_cycles", sa.Integer), sa.Column("max_voltage_V", sa.Float),
        sa.Column("max_nominal_field_V_per_m", sa.Float), sa.Column("breakdown_field_V_per_m", sa.Float),
        sa.Column("figures", text), sa.Column("fits", text),
        sa.Column("signature", text),  # the files the row was read from ('' : written at a run's start)
    )


# SQLite catalogues' engines, tables and compiled statements, kept across Catalog objects of this process (a run
# writes two rows, a benchmark many runs): building them again for every row cost more CPU than the rows' SQL
_SHARED: dict[tuple[str, str], tuple[sa.Engine, sa.MetaData, sa.Table]] = {}
_SHARED_LOCK = threading.Lock()
SHARED_ENGINES = 16  # catalogues kept (the oldest is let go)


class Catalog:
    """A connection to one catalogue (created on first use); every write is its own transaction."""

    def __init__(self, url: str) -> None:
        import sqlalchemy as sa

        self.url = url
        try:
            parsed = sa.engine.make_url(url)
        except sa.exc.ArgumentError:
            raise ValueError(f"catalogue {url!r}: not a database URL (e.g. sqlite:///runs/catalog.sqlite or "
                             "postgresql+psycopg://user@host/db)") from None
        kwargs: dict[str, Any] = {}
        if parsed.get_backend_name() == "sqlite":
            if parsed.database:
                Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
            kwargs["connect_args"] = {"timeout": SQLITE_BUSY_S}
        elif parsed.get_backend_name() == "postgresql":
            kwargs["connect_args"] = {  # libpq's: no wait on the shared server may hold a run for long
                "connect_timeout": PG_CONNECT_S,
                "options": f"-c statement_timeout={PG_STATEMENT_S * 1000} -c lock_timeout={PG_STATEMENT_S * 1000}",
                "keepalives": 1, "keepalives_idle": PG_KEEPALIVE_S, "keepalives_interval": PG_KEEPALIVE_S,
                "keepalives_count": 2}
        self.backend = parsed.get_backend_name()
        self.display = parsed.render_as_string(hide_password=True)
        shared = self.backend == "sqlite" and parsed.database not in (None, "", ":memory:")
        key = (parsed.render_as_string(hide_password=False), repr(sorted(kwargs.items())))
        with _SHARED_LOCK:
            found = _SHARED.get(key) if shared else None
            if found is None:
                try:  # a shared one opens a connection per transaction: none outlives it (file replaced, fork)
                    engine = sa.create_engine(parsed, **kwargs, **({"poolclass": sa.pool.NullPool} if shared else {}))
                except (ImportError, sa.exc.ArgumentError) as exc:
                    raise ValueError(f"catalogue {parsed.render_as_string()}: {exc}") from None
                md = sa.MetaData()
                found = (engine, md, _table(md))
                if shared:
                    _SHARED[key] = found
                    while len(_SHARED) > SHARED_ENGINES:
                        _SHARED.pop(next(iter(_SHARED)))
        self.engine, self.md, self.runs = found
        self._shared = shared
        self._create()  # every time: a catalogue file deleted since is created again

    def _create(self) -> None:
        import sqlalchemy as sa

        for attempt in range(3):  # two benches creating the schema at once: one of them loses the race
            try:
                self.md.create_all(self.engine, checkfirst=True)
                return
            except (sa.exc.IntegrityError, sa.exc.ProgrammingError, sa.exc.OperationalError) as exc:
                if attempt == 2 or ("already exists" not in str(exc) and "duplicate" not in str(exc).lower()):
                    raise

    def close(self) -> None:
        if not self._shared:  # a shared engine holds no connection between transactions
            self.engine.dispose()

    def __enter__(self) -> Catalog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def upsert(self, rows: Iterable[dict[str, Any]], *, start: bool = False) -> None:
        """Insert or replace rows (by host and path), in one transaction; ``start``: rows written at a run's
        start, which never replace a row read from the same run's file (a late start row after the end row)."""
        import sqlalchemy as sa

        rows = list(rows)
        if not rows:
            return
        if self.backend == "postgresql":
            from sqlalchemy.dialects.postgresql import insert
        else:
            from sqlalchemy.dialects.sqlite import insert  # type: ignore[assignment]  # same upsert API, other class
        stmt = insert(self.runs)
        keys = {"host", "path"}
        t = self.runs
        where = sa.or_(t.c.signature == "", t.c.signature.is_(None),
                       t.c.run_id.is_distinct_from(stmt.excluded.run_id)) if start else None
        stmt = stmt.on_conflict_do_update(index_elements=["host", "path"],
                                          set_={c: stmt.excluded[c] for c in COLUMNS if c not in keys}, where=where)
        with self.engine.begin() as conn:
            conn.execute(stmt, rows)

    def delete(self, host: str, paths: Iterable[str]) -> None:
        paths = list(paths)
        if not paths:
            return
        with self.engine.begin() as conn:
            for k in range(0, len(paths), 500):
                conn.execute(self.runs.delete().where(self.runs.c.host == host,
                                                      self.runs.c.path.in_(paths[k:k + 500])))

    def rows(self, *, host: str | None = None, under: Path | None = None, paths: Iterable[str] | None = None,
             specimen: str | None = None, protocol: str | None = None, since: str | None = None,
             state: str | None = None) -> list[dict[str, Any]]:
        """Rows in start order, filtered; ``under``: only files in that folder (and below); ``paths``: only these
        (resolved) paths."""
        import sqlalchemy as sa

        t = self.runs
        q = sa.select(t)
        if host is not None:
            q = q.where(t.c.host == host)
        if under is not None:
            prefix = str(under.resolve()).rstrip("/") + "/"
            q = q.where(t.c.path.startswith(prefix, autoescape=True))
        if paths is not None:
            wanted = sorted(set(paths))
            if not wanted:
                return []
            if len(wanted) > 500:  # a long IN list: ask for them all, keep these
                keep = set(wanted)
                return [r for r in self.rows(host=host, under=under, specimen=specimen, protocol=protocol,
                                             since=since, state=state) if r["path"] in keep]
            q = q.where(t.c.path.in_(wanted))
        if specimen is not None:
            q = q.where(t.c.specimen_id == specimen)
        if protocol is not None:
            q = q.where(t.c.protocol_name == protocol)
        if since is not None:
            q = q.where(t.c.start_time >= since)
        if state is not None:  # ENDED: the files that say "running" whose writer is gone; PAUSED: held, under way
            q = q.where(t.c.state == ("running" if state in (ENDED, PAUSED) else state))
        with self.engine.connect() as conn:
            out = [dict(r._mapping) for r in conn.execute(q.order_by(t.c.start_time, t.c.path))]
        if state == ENDED:  # crashed or killed, or ended unstamped (a full disk): what --state running leaves out
            out = [r for r in out if shown_state(r) not in ("running", PAUSED)]
        elif state is not None:  # as listed: a file whose writer is gone says "running" and is not (a tester)
            out = [r for r in out if shown_state(r) == state]
        return out


# ---- rows from files ----------------------------------------------------------------------------------------------


ENDED = "ended"  # a --state of its own: the runs whose file says running and whose writer is gone (not stamped)
PAUSED = "paused"  # a --state of its own: the runs under way that are paused (the file says running)


def shown_state(row: dict[str, Any]) -> str:
    """The state of a row as listings show it (:func:`~bench.storage.runfile.state_shown`)."""
    from bench.storage.runfile import state_shown

    return state_shown(row["state"] or "", bool(row["complete"]), row["incomplete_reason"] or "")


def host_name() -> str:
    return socket.gethostname()


def _abs(p: Path) -> str:
    return str(p.resolve())


def _stat(p: Path) -> list[int] | None:
    try:
        st = p.stat()
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


def report_dir(path: Path) -> Path:
    """Where ``bench report`` writes a run's figures by default (``<stem>-report``, with figures.json)."""
    return path.with_name(path.stem + "-report")


def fit_file(path: Path) -> Path:
    """The fit file ``bench fit`` writes beside a run (``x.h5`` → ``x.fit.hdf5``: bench/identify/store.py)."""
    return path.with_name(path.stem + ".fit.hdf5")


def signature(path: Path) -> str:
    """What a row read from ``path`` depends on: the run file, its fit file and its report's figures."""
    return json.dumps({"run": _stat(path), "fit": _stat(fit_file(path)),
                       "figures": _stat(report_dir(path) / "figures.json")})


def row_from_attrs(path: Path, attrs: dict[str, Any]) -> dict[str, Any]:
    """The row of a run that has just started (from the attributes it writes into its file)."""
    prev = attrs.get("previous_file")
    return {**{c: None for c in COLUMNS}, "host": host_name(), "path": _abs(path),
            "run_id": _s(attrs.get("run_id")), "campaign_id": _s(attrs.get("campaign_id")),
            "protocol_name": _s(attrs.get("protocol_name")), "protocol_sha256": _s(attrs.get("protocol_sha256")),
            "rig": _s(attrs.get("rig_name")), "specimen_id": _s(attrs.get("specimen_id")),
            "operator": _s(attrs.get("operator")), "notes": _s(attrs.get("notes")), "state": "running",
            "complete": False, "reason": "", "incomplete_reason": "no end recorded yet",
            "start_time": _s(attrs.get("start_time")), "end_time": "", "steps_completed": 0,
            "previous_file": _abs(path.parent / str(prev)) if prev else None, "figures": "[]", "fits": "[]",
            "signature": ""}


def _s(v: Any) -> str | None:
    return None if v is None else str(v)


def row_from_file(path: Path, hv: HvStats | None = None) -> dict[str, Any]:
    """The row of a run file, read from the file (and its fit file and report). ValueError if it is not one.
    ``hv``: the file's :func:`hv_statistics` already known (its recorder's :class:`HvAccumulator`), not read again."""
    from bench.storage.runfile import open_run

    sig = signature(path)  # before reading: a change while reading makes the next reconcile read it again
    run = open_run(path, streams=False)
    return _end_row(path, run.attrs, sig, hv, state=run.state, complete=bool(run.complete), reason=run.reason,
                    incomplete_reason=run.incomplete_reason or None, end_time=run.end_time,
                    steps_completed=len(run.completed_steps()), steps_total=int(run.program.shape[0]))


def row_from_written(path: Path, written: Written, hv: HvStats | None = None) -> dict[str, Any]:
    """The row of the run file a recorder has just finished, from its account of what it wrote (:meth:`~bench.
    storage.recorder.Recorder.written`) — the row :func:`row_from_file` reads, without reading the file again — or
    read from the file where it changed since the recorder closed it."""
    sig = signature(path)
    if json.loads(sig)["run"] != list(written.file_stat):
        return row_from_file(path, hv)
    return _end_row(path, written.attrs, sig, hv, in_file=False, state=written.state, complete=True,
                    reason=written.reason, incomplete_reason=None, end_time=written.end_time,
                    steps_completed=written.steps_completed, steps_total=written.steps_total)


def _end_row(path: Path, attrs: dict[str, Any], sig: str, hv: HvStats | None, in_file: bool = True,
             **end: Any) -> dict[str, Any]:
    """A row from a run file's root attributes, its end (``end``: the columns of its state and steps) and its
    statistics; ``in_file``: the run file may hold fits (False: a file the recorder wrote holds none)."""
    row = row_from_attrs(path, attrs)
    first = int(attrs.get("resumed_at_step") or 0)  # a resumed file runs its protocol's steps from there on: its
    end["steps_total"] = max(end["steps_total"] - first, 0)  # count (a finished one read "4/6": an outside tester)
    stats = hv if hv is not None else hv_statistics(path)
    spec = _specimen(path, attrs)
    row.update({
        **end,
        "hv_time_s": stats.hv_time_s, "hv_cycles": stats.cycles, "max_voltage_V": stats.max_voltage_V,
        "max_nominal_field_V_per_m": stats.max_voltage_V / spec[0] if spec[0] else None,
        "breakdown_field_V_per_m": spec[1], "figures": json.dumps(_figures(path)),
        "fits": json.dumps(_fits(path, attrs, in_file)),
        "signature": sig,
    })
    return row


def _specimen(path: Path, attrs: dict[str, Any]) -> tuple[float | None, float | None]:
    """(reference thickness [m], breakdown field [V/m]) of the model stored in the run file (None if absent, or not
    numbers: a catalogue row is no place to refuse a file). Read through the runs' one reader of the attribute."""
    from bench.storage.runfile import specimen_of

    try:
        model = specimen_of(attrs, path).get("model", {})
        if "L3" in model:  # membrane (thesis): E = Φλ²/L3; failure where the true field exceeds breakdown_field
            return float(model["L3"]), _f(model.get("breakdown_field"))
        if "t0" in model:  # LS-DEA: E_B = E0 λ3^(−r/2), E0 at λ3 = 1
            return float(model["t0"]), _f(model.get("material", {}).get("E0"))
    except (ValueError, TypeError, AttributeError):  # an edited attribute: a null, a string where an object was
        return None, None
    return None, None


class TrueField(NamedTuple):
    """A run's highest true field [V/m], its highest ratio to the breakdown field at the same instant (None where
    the model gives no breakdown field) and the kind of specimen ("membrane": a constant breakdown field; "lsdea":
    one that grows with the stretch)."""

    field: float
    ratio: float | None
    kind: str


def peak_true_field(path: str | Path) -> TrueField | None:
    """:class:`TrueField` of a run, over its measured voltage samples, read in chunks; None where it is not known
    (no voltage record, no stretch known, a file that cannot be read).

    * membrane: E = |V| λ²/L3 (physics.md §1.2), λ = λ_pre + u/L_d with the laser's displacement u interpolated at
      each voltage sample (the supervisor's estimate, from the model stored in the file); E_B a constant;
    * LS-DEA: E = |V| λ1λ2/t0, E_B = E0 λ3^(−r/2) = E0 (λ1λ2)^(r/2) (physics.md, Model B), λ1 = λ1p x/xp,
      λ2 = λ2p y/yp, y = √(4l² − x²), at the aperture x of each sample: the motor's recorded aperture, the blocked
      aperture, or the laser's value on a hung specimen (as the supervisor reads it); λ2p the prototype's at the
      sample's time (a set step may change it). E_B grows with the stretch, so the ratio's peak is taken sample by
      sample, not as the peak field over one breakdown field."""
    from bench.storage.chunks import open_source
    from bench.storage.runfile import specimen_of

    best: TrueField | None = None
    try:
        with open_source(path) as src:
            spec = specimen_of(src.run.attrs, Path(path))
            model, s = spec.get("model", {}), src.streams
            if not s.length.get("amplifier"):
                return None
            how = _membrane_field(model) if "L3" in model else _lsdea_field(model, spec, src) if "t0" in model \
                else None
            if how is None or not s.length.get(how.stream or "amplifier"):
                return None
            for chunk in s.chunks("amplifier"):
                t, v = chunk["t"].astype(float), np.abs(chunk["voltage"].astype(float))
                t, v = t[np.isfinite(v)], v[np.isfinite(v)]
                if not t.size:
                    continue
                if how.stream is not None:
                    w = s.window(how.stream, float(t.min()), float(t.max()), [how.column], neighbours=True,
                                 finite=how.column)
                    if not w["t"].size:
                        continue
                    where = np.interp(t, w["t"].astype(float), w[how.column].astype(float))
                else:
                    where = np.full(t.shape, how.constant)
                e, ratio = how.at(t, v, where)
                ok = np.isfinite(e)
                if not ok.any():
                    continue
                peak = float(np.max(e[ok]))
                r_peak = float(np.max(ratio[ok])) if ratio is not None else None
                best = TrueField(peak, r_peak, how.kind) if best is None else TrueField(
                    max(best.field, peak), None if best.ratio is None or r_peak is None else max(best.ratio, r_peak),
                    how.kind)
    except (ValueError, OSError, KeyError, TypeError, AttributeError, ArithmeticError):  # unreadable, edited (a
        return None  # prototype of inf: OverflowError): not known
    return best


@dataclass
class _FieldModel:
    """How a run's true field follows from its voltage and one recorded quantity (``stream``/``column``, or
    ``constant`` where none is recorded: a blocked aperture): ``at(t, |V|, that quantity)`` → (E, E/E_B or None)."""

    kind: str
    stream: str | None
    column: str
    constant: float
    at: Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray | None]]


def _membrane_field(model: dict[str, Any]) -> _FieldModel:
    """The membrane's: E = |V| λ²/L3, λ = λ_pre + u/L_d; E_B the model's breakdown field (a constant)."""
    l3, l_d, pre = float(model["L3"]), float(model["L_d"]), float(model["lambda_pre"])
    e_b = _f(model.get("breakdown_field"))

    def at(_t: np.ndarray, v: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        lam = pre + u / l_d
        e = v * lam * lam / l3
        return e, (e / e_b if e_b else None)

    return _FieldModel("membrane", "laser", "displacement", math.nan, at)


def _lsdea_field(model: dict[str, Any], spec: dict[str, Any], src: Any) -> _FieldModel:
    """The LS-DEA's: E = |V| λ1λ2/t0 and E_B = E0 (λ1λ2)^(r/2) at the aperture x (:func:`peak_true_field`)."""
    from bench.models.lozenge import PROTOTYPE_LAMBDA2P

    l, xp, t0 = float(model["l"]), float(model["xp"]), float(model["t0"])
    material = model.get("material", {})
    e0, r = _f(material.get("E0")), float(material.get("r", 0.0))
    lam2p0 = float(model["lambda2p"])
    changes = [(te, PROTOTYPE_LAMBDA2P[int(values["prototype"])]) for te, values in src.run.specimen_changes()
               if "prototype" in values and int(values["prototype"]) in PROTOTYPE_LAMBDA2P]
    yp = math.sqrt(4 * l * l - xp * xp)

    def at(t: np.ndarray, v: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        lam2p = np.full(t.shape, lam2p0)
        for te, value in changes:  # each change holds from its time on (RunFile.specimen_at)
            lam2p[t + 1e-9 >= te] = value
        x = np.clip(x, 1e-9, 2 * l * (1 - 1e-12))  # a reading off the mechanism's range: its nearest end
        stretch = (x / xp) * np.sqrt(4 * l * l - x * x) / yp * lam2p ** 0.5  # λ1λ2 = λ1p λ2p x y/(xp yp)
        e = v * stretch / t0
        return e, (e / (e0 * stretch ** (r / 2)) if e0 else None)

    cfg = spec.get("lsdea", {})
    how = cfg.get("configuration", "motor")
    if how == "blocked":
        return _FieldModel("lsdea", None, "", float(cfg["blocked_position_m"]), at)
    if how == "hung":
        return _FieldModel("lsdea", "laser", "displacement", math.nan, at)
    return _FieldModel("lsdea", "motor", "aperture", math.nan, at)


TRUE_FIELD_CACHE = "true-field.json"  # in the user's cache folder: each run file's peak true field, by size and time


def _cache_file() -> Path:
    """The peak-true-field cache (``$XDG_CACHE_HOME`` or ~/.cache, ``dea-bench/``): only a saving of time — lost or
    unreadable, each file is read again."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "dea-bench" / TRUE_FIELD_CACHE


class TrueFields:
    """:func:`peak_true_field` of run files, each read once while it is unchanged (its size and modification time):
    a specimen's history reads every run's whole amplifier stream, which for overnight 10-kHz runs is minutes of
    reading at every ``bench specimen show`` (a reviewer). Kept in :func:`_cache_file` between calls."""

    def __init__(self) -> None:
        self.path = _cache_file()
        try:
            loaded = json.loads(self.path.read_text(encoding="utf-8"))
            self.known: dict[str, Any] = loaded if isinstance(loaded, dict) else {}
        except (OSError, ValueError):
            self.known = {}
        self.changed = False

    def __call__(self, path: str) -> TrueField | None:
        try:
            st = os.stat(path)
        except OSError:
            return None
        key, stamp = str(Path(path).resolve()), [st.st_size, st.st_mtime_ns]
        hit = self.known.get(key)
        if isinstance(hit, dict) and hit.get("stamp") == stamp and "kind" in hit:  # (no kind: an older cache's)
            value, ratio = hit.get("field"), hit.get("ratio")
            if not isinstance(value, (int, float)):
                return None
            return TrueField(float(value), float(ratio) if isinstance(ratio, (int, float)) else None, str(hit["kind"]))
        found = peak_true_field(path)
        self.known[key] = {"stamp": stamp, **(found._asdict() if found else {"field": None, "ratio": None,
                                                                              "kind": ""})}
        self.changed = True
        return found

    def save(self) -> None:
        """Write the cache (atomically; a folder that cannot take it: the next call reads the files again)."""
        if not self.changed:
            return
        with contextlib.suppress(OSError):
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}")
            tmp.write_text(json.dumps(self.known), encoding="utf-8")
            os.replace(tmp, self.path)


def _f(v: Any) -> float | None:
    return None if v is None else float(v)


def _figures(path: Path) -> list[dict[str, Any]]:
    p = report_dir(path) / "figures.json"
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    return data if isinstance(data, list) else []


def _fits(path: Path, attrs: dict[str, Any], in_file: bool = True) -> list[dict[str, Any]]:
    """The fits stored with a run — ``/fit/<model>-<n>`` groups in the run file and in its fit file (layout:
    bench/identify/store.py), oldest first — as model, when, rms, records (file names) and the parameters. A fit file
    of another run of the same name (start time or protocol hash differ) is not this run's: left out. Read with
    h5py alone (no identification code: this runs at every run's end)."""
    from bench.storage.runfile import open_h5

    groups: list[dict[str, Any]] = []

    def read(f: Any) -> None:
        if "fit" not in f:
            return
        for g in f["fit"].values():
            names = [n.decode() if isinstance(n, bytes) else str(n) for n in g["names"][:]]
            units = [u.decode() if isinstance(u, bytes) else str(u) for u in g["units"][:]] if "units" in g else []
            try:
                records = [Path(str(r)).name for r in json.loads(str(g.attrs.get("records", "[]")))]
            except ValueError:
                records = []
            groups.append({"model": _text(g.attrs.get("model", "")), "created": _text(g.attrs.get("created", "")),
                           "rms": _f(g.attrs.get("rms")), "records": records,
                           "parameters": {n: float(v) for n, v in zip(names, g["values"][:], strict=True)},
                           "units": dict(zip(names, units, strict=False)),
                           "mixed_specimens": _text(g.attrs.get("mixed_specimens", ""))})

    try:
        if in_file:
            with open_h5(path) as f:
                read(f)
        side = fit_file(path)
        if side.is_file():
            import h5py

            with h5py.File(side, "r") as f:
                if (_text(f.attrs.get("run_start_time", "")) == str(attrs.get("start_time", ""))
                        and _text(f.attrs.get("protocol_sha256", "")) == str(attrs.get("protocol_sha256", ""))):
                    read(f)
    except (ValueError, OSError, KeyError):
        pass  # an unreadable fit is no fit; the run's own row stands
    return sorted(groups, key=lambda d: d["created"])


def _text(v: Any) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def hv_statistics(path: Path, threshold: float = HV_THRESHOLD_V) -> HvStats:
    """Time under high voltage, high-voltage cycles and peak |V| from the measured amplifier voltage, read in
    chunks (see the module's docstring for the definitions). Zero for a file with no amplifier stream."""
    from bench.storage.runfile import open_h5, valid_counts

    acc = HvAccumulator(threshold)
    chunk = hv_stats.CHUNK
    with open_h5(path) as f:
        if "amplifier" not in f or "voltage" not in f["amplifier"]:
            return HvStats(0.0, 0, 0.0)
        g = f["amplifier"]
        for d in (g["t"], g["voltage"]):
            d.refresh()
        n = min(g["t"].shape[0], g["voltage"].shape[0])
        n = min(n, valid_counts(f, path).get("amplifier", n))
        for k in range(0, n, chunk):
            acc.chunk(g["t"][k:min(k + chunk, n)], g["voltage"][k:min(k + chunk, n)])
    return acc.stats()


# ---- keeping the catalogue true to the files ----------------------------------------------------------------------


def run_files(folder: Path) -> Iterator[Path]:
    """The run files (``*.h5``) in ``folder`` and below, by name."""
    yield from sorted(p for p in folder.rglob("*.h5") if p.is_file())


# what a database says when a write is refused by the medium or the rights, not by the query: a read-only folder or
# file ("attempt to write a readonly database", "unable to open database file"), a full disk, a read-only role
_WRITE_REFUSED = ("readonly", "read-only", "read only", "disk is full", "disk full", "no space", "unable to open",
                  "permission denied")


def write_refused(exc: BaseException) -> str | None:
    """Why a catalogue write failed, in one line, where the medium or the rights refused it (read-only, full disk);
    None for any other failure."""
    import sqlalchemy as sa

    if not isinstance(exc, sa.exc.DBAPIError):
        return None
    why = " ".join(str(getattr(exc, "orig", None) or exc).split())[:300]
    return why if any(w in why.lower() for w in _WRITE_REFUSED) else None


_DAMAGED = ("file is not a database", "database disk image is malformed")  # SQLite's words for a damaged file


def damaged_file(exc: BaseException, url: str) -> Path | None:
    """The SQLite catalogue file of ``url`` where ``exc`` says it is damaged (not a database, a malformed image);
    None for any other failure or database. The catalogue is an index of the run files: a damaged one is set aside
    (:func:`set_aside`) and made again from the files, never repaired in place."""
    import sqlalchemy as sa

    if not isinstance(exc, sa.exc.DatabaseError):
        return None
    why = str(getattr(exc, "orig", None) or exc).lower()
    parsed = sa.engine.make_url(url)
    if parsed.get_backend_name() != "sqlite" or parsed.database in (None, "", ":memory:") \
            or not any(w in why for w in _DAMAGED):
        return None
    return Path(parsed.database)


def set_aside(path: Path) -> Path:
    """Move a damaged catalogue file aside (``catalog.sqlite.damaged-<UTC time>``, kept for whoever wants to look
    at it) so that a new one is made in its place; returns where it went."""
    from datetime import UTC, datetime

    moved = path.with_name(f"{path.name}.damaged-{datetime.now(UTC).strftime('%Y%m%dT%H%M%S.%fZ')}")
    os.replace(path, moved)
    for suffix in ("-journal", "-wal", "-shm"):  # its own journal files belong to it, not to the new one
        with contextlib.suppress(OSError):
            os.replace(path.with_name(path.name + suffix), moved.with_name(moved.name + suffix))
    return moved


class CatalogNotWrittenError(Exception):
    """:func:`reconcile` read the folder but could not write what it found (``why``: read-only medium, full disk);
    ``done``: what it found (the rows' paths in ``found``)."""

    def __init__(self, why: str, done: Reconciled) -> None:
        super().__init__(why)
        self.why, self.done = why, done


def memory_copy(url: str) -> Catalog | None:
    """An in-memory catalogue holding the rows of the SQLite catalogue ``url`` (read through a read-only
    connection: the file may lie on a read-only or full medium; none there yet: empty), for a read command to
    reconcile and list when the file cannot be written; None for another database (a shared server)."""
    import sqlite3

    import sqlalchemy as sa

    parsed = sa.engine.make_url(url)
    if parsed.get_backend_name() != "sqlite" or parsed.database in (None, "", ":memory:"):
        return None
    cat = Catalog("sqlite://")  # one connection per thread for a memory database: the rows stay while cat does
    path = Path(parsed.database)
    if path.is_file():
        src = sqlite3.connect(f"{path.resolve().as_uri()}?mode=ro", uri=True)
        try:
            with cat.engine.connect() as conn:
                src.backup(conn.connection.driver_connection)  # type: ignore[arg-type]
        finally:
            src.close()
        cat._create()  # a file without the table yet
    return cat


@dataclass
class Reconciled:
    added: int = 0
    updated: int = 0
    removed: int = 0
    unreadable: list[str] = field(default_factory=list)
    found: set[str] = field(default_factory=set)  # the rows' paths of the run files found there (links resolved)


def _maybe_gone(row: dict[str, Any]) -> bool:
    """Whether a row read from an unchanged file says its run is still going: its writer may have died since (a
    killed run's file does not change), so the file is read again — once it says so, the row no longer asks. A
    paused run too (its file may stand still while paused, and a kill then leaves it so: a reviewer)."""
    return not row["complete"] and row["state"] == "running" and shown_state(row) in ("running", PAUSED)


def reconcile(cat: Catalog, folder: Path, rebuild: bool = False) -> Reconciled:
    """Make the rows of this host's files under ``folder`` those the files give: rows of changed or new files
    re-read, rows of missing files removed (``rebuild``: every row re-read). A file linked into the folder from
    elsewhere is one of its files, its row (keyed on the resolved path) the one row of that file. Files that are not
    run files are listed in ``unreadable``; the rows' paths of the others in ``found``."""
    folder = folder.resolve()
    if not folder.is_dir():
        raise ValueError(absent_runs_folder(folder))
    host = host_name()
    files = {_abs(p): p for p in run_files(folder)}
    prefix = str(folder).rstrip("/") + "/"
    have = {r["path"]: r for r in cat.rows(host=host, under=folder)}
    have.update({r["path"]: r for r in cat.rows(host=host, paths=[k for k in files if not k.startswith(prefix)])})
    out = Reconciled()
    rows, seen = [], set()
    for key, p in files.items():
        seen.add(key)
        old = have.get(key)
        if (not rebuild and old is not None and old["signature"] and old["signature"] == signature(p)
                and not _maybe_gone(old)):
            out.found.add(key)
            continue
        try:
            rows.append(row_from_file(p))
        except (ValueError, OSError, KeyError) as exc:
            out.unreadable.append(f"{p}: {' '.join(str(exc).split())}")
            continue
        out.found.add(key)
        if old is None:
            out.added += 1
        else:
            out.updated += 1
    gone = [k for k in have if k not in seen]  # a linked file's row is in have only while it is seen
    out.removed = len(gone)
    try:
        if rebuild:
            cat.delete(host, list(have))
        else:
            cat.delete(host, gone)
        cat.upsert(rows)
    except Exception as exc:  # a read-only or full medium: the caller may still list (CatalogNotWrittenError says what)
        if (why := write_refused(exc)) is None:
            raise
        raise CatalogNotWrittenError(why, out) from exc
    return out


def in_folder(folder: Path, host: str | None = None, found: Collection[str] = ()) -> Callable[[dict[str, Any]], bool]:
    """Whether a row's file is in ``folder`` (or below) on ``host`` (default: this host): its path is, or it is one
    of ``found`` (:attr:`Reconciled.found`: files found in the folder, a file linked into it among them)."""
    prefix, host = str(folder.resolve()).rstrip("/") + "/", host if host is not None else host_name()
    return lambda row: row["host"] == host and (str(row["path"]).startswith(prefix) or row["path"] in found)


def one_per_run(rows: list[dict[str, Any]], prefer: Path | None = None,
                found: Collection[str] = ()) -> list[dict[str, Any]]:
    """One row per run: files that are copies of one run (the same run ID: a backup, a folder copied with its
    catalogue) count once. The row kept is the copy in ``prefer`` (the folder asked about; ``found``: as for
    :func:`in_folder`) on this host, else one on this host, else the most complete (complete, most steps), else the
    least deep, else the first by path. Returns the rows kept, in their order, each with ``copies``: the other
    copies' paths (``host:path`` for another host's)."""
    host = host_name()
    inside = in_folder(prefer, host, found) if prefer is not None else lambda r: False

    def rank(r: dict[str, Any]) -> tuple[bool, bool, bool, int, int, str, str]:
        return (not inside(r), r["host"] != host, not r["complete"], -(r["steps_completed"] or 0),
                str(r["path"]).count("/"), r["host"], r["path"])

    groups: dict[tuple[str, ...], list[dict[str, Any]]] = {}
    for r in rows:  # a row without a run ID (an older file) is a run of its own
        groups.setdefault(("id", r["run_id"]) if r["run_id"] else ("file", r["host"], r["path"]), []).append(r)
    chosen: dict[int, list[str]] = {}
    for group in groups.values():
        best, *others = sorted(group, key=rank)
        chosen[id(best)] = [o["path"] if o["host"] == host else f"{o['host']}:{o['path']}" for o in others]
    return [{**r, "copies": chosen[id(r)]} for r in rows if id(r) in chosen]


# ---- the run's hooks: never let the catalogue stop or fail a run ---------------------------------------------------


def db_reason(exc: BaseException) -> str:
    """What a database error says, in one line: the driver's own message (SQLAlchemy's error wraps it, ``orig``,
    and adds the whole SQL statement and its parameters, which a full disk dumped into the run's warning), at most
    300 characters."""
    cause = getattr(exc, "orig", None) or exc
    return " ".join(str(cause).split())[:300] or type(cause).__name__


def record_start(path: Path, attrs: dict[str, Any], url: str | None = None) -> None:
    """Catalogue a run that has just started; on any failure one warning line (the run goes on)."""
    try:
        with Catalog(catalog_url(path.parent, url)) as cat:
            cat.upsert([row_from_attrs(path, attrs)], start=True)
    except Exception as exc:  # the catalogue is an index: a run never depends on it
        log.warning("run catalogue not written at the start (the run goes on; `bench runs list` reconciles it "
                    "from the files): %s", db_reason(exc))


def record_end(path: Path, url: str | None = None, hv: HvStats | None = None, written: Written | None = None) -> None:
    """Catalogue a run that has ended, from its file (``hv``: its high-voltage statistics, as the recorder counted
    what it wrote: :meth:`~bench.storage.recorder.Recorder.hv_stats`; ``written``: the recorder's account of the
    finished file, :func:`row_from_written`, instead of reading it again); on any failure one warning line."""
    url = catalog_url(path.parent, url)
    bound = SQLITE_BUSY_S if url.startswith("sqlite") else PG_CONNECT_S + PG_STATEMENT_S
    notice = threading.Timer(WAIT_NOTICE_S, lambda: log.warning(
        "run catalogue %s: waiting for it (another writer holds it, or its server is slow; up to %g s); the run "
        "file is complete, and "
        "Ctrl-C skips the catalogue's row (`bench runs list` reconciles it)", sa_display(url), bound))
    notice.daemon = True
    try:
        # the file's row first, unwatched: a long file read here was said as a wait for the catalogue (a reviewer)
        row = row_from_written(path, written, hv) if written is not None else row_from_file(path, hv)
        notice.start()  # a catalogue another bench holds made the CLI wait ~55 s after a run saying nothing (tester)
        with Catalog(url) as cat:
            cat.upsert([row])
    except Exception as exc:
        log.warning("run catalogue not written at the end (`bench runs list` reconciles it from the files): %s",
                    db_reason(exc))
    finally:
        notice.cancel()


def sa_display(url: str) -> str:
    """A database URL as said in a line: its password hidden."""
    import sqlalchemy as sa

    return sa.engine.make_url(url).render_as_string(hide_password=True)


# ---- a specimen's life -------------------------------------------------------------------------------------------


def specimen_history(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """A specimen's runs in start order with cumulative high-voltage time and cycles, its peak nominal field (|V| over
    the unstretched thickness) and its peak true field against the model's breakdown field (``field_ratio``: true
    over breakdown, None where no run's true field is known), the runs that failed or did not finish, and each
    fitted parameter over its life (a fit stored with every file of a campaign counts once, at the last of them)."""
    from bench.storage.runfile import state_shown

    runs, cum_t, cum_c = [], 0.0, 0
    best: tuple[float, float | None, str] | None = None  # (nominal field, breakdown field, file)
    true: tuple[float, float | None, str] | None = None  # (true field, breakdown field, file)
    ratio: tuple[float, str] | None = None  # (true field over the breakdown field at the same instant, file)
    kinds: set[str] = set()  # of the runs whose true field is known
    fits: dict[tuple[str, str, str], tuple[int, dict[str, Any], str]] = {}
    failures = []
    across: set[tuple[str, str]] = set()  # fits across several specimens, left out of the parameters' history
    true_field = TrueFields()
    for r in sorted(rows, key=lambda r: (r["start_time"] or "", r["path"])):
        cum_t += r["hv_time_s"] or 0.0
        cum_c += r["hv_cycles"] or 0
        field = r["max_nominal_field_V_per_m"]
        if field is not None and (best is None or field > best[0]):
            best = (field, r["breakdown_field_V_per_m"], r["path"])
        known = true_field(r["path"]) if field is not None else None
        e_true = known.field if known is not None else None
        if e_true is not None and (true is None or e_true > true[0]):
            true = (e_true, r["breakdown_field_V_per_m"], r["path"])
        if known is not None and known.ratio is not None and (ratio is None or known.ratio > ratio[0]):
            ratio = (known.ratio, r["path"])
        if known is not None:
            kinds.add(known.kind)
        if r["state"] in ("tripped", "error", "interrupted") or not r["complete"]:  # (a stopped run did not finish
            # its protocol either: a SIGTERM-interrupted run at 0/2 steps was left out, outside tester)
            failures.append({"file": r["path"], "state": r["state"],
                             "state_shown": state_shown(r["state"], bool(r["complete"]), r["incomplete_reason"] or ""),
                             "reason": r["incomplete_reason"] if not r["complete"] else r["reason"]})
        for fit in json.loads(r["fits"] or "[]"):
            if fit.get("mixed_specimens"):  # fitted across specimens (`bench fit` warned): no point of this one's life
                across.add((fit["model"], fit["created"]))  # (it entered it unmarked, a second tester)
                continue
            # a campaign fit is stored with each of its files (each copy stamped when written): one fit, one key
            key = (fit["model"], json.dumps(fit.get("records", [])), json.dumps(fit["parameters"], sort_keys=True))
            fits[key] = (cum_c, fit, r["path"])  # the last file holding it wins
        runs.append({"file": r["path"], "start_time": r["start_time"], "protocol": r["protocol_name"],
                     "state": r["state"], "complete": bool(r["complete"]),
                     "state_shown": state_shown(r["state"], bool(r["complete"]), r["incomplete_reason"] or ""),
                     "steps": f"{r['steps_completed'] or 0}/{r['steps_total'] or 0}",
                     "previous_file": r["previous_file"], "copies": r.get("copies", []),
                     "hv_time_s": r["hv_time_s"], "hv_cycles": r["hv_cycles"],
                     "cumulative_hv_time_s": cum_t, "cumulative_cycles": cum_c,
                     "max_nominal_field_V_per_m": field, "max_true_field_V_per_m": e_true})
    true_field.save()
    params: dict[str, list[dict[str, Any]]] = {}
    for cycles, fit, path in sorted(fits.values(), key=lambda x: (x[0], x[1]["created"])):
        for name, value in fit["parameters"].items():
            params.setdefault(name, []).append({"cumulative_cycles": cycles, "value": value,
                                                "unit": fit.get("units", {}).get(name, ""), "model": fit["model"],
                                                "created": fit["created"], "file": path})
    # like with like: the breakdown field is a true-field limit, so only the true field is divided by it — sample by
    # sample (an LS-DEA's breakdown field grows with its stretch: its peak ratio need not be at its peak field)
    return {"runs": runs, "hv_threshold_V": HV_THRESHOLD_V, "hv_time_s": cum_t, "hv_cycles": cum_c,
            "max_nominal_field_V_per_m": best[0] if best else None,
            "max_true_field_V_per_m": true[0] if true else None, "max_true_field_file": true[2] if true else None,
            "breakdown_field_V_per_m": (true or best or (None, None))[1],
            "field_ratio": ratio[0] if ratio else None, "field_ratio_file": ratio[1] if ratio else None,
            "stretch_dependent_breakdown": "lsdea" in kinds,
            "max_field_file": best[2] if best else None, "failures": failures, "parameters": params,
            "fits_across_specimens": len(across)}


def plot_history(history: dict[str, Any], specimen: str, out: Path) -> Path | None:
    """Each fitted parameter against the cumulative cycles (PNG); None when nothing was fitted."""
    params = history["parameters"]
    if not params:
        return None
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n = len(params)
    cols = min(3, n)
    rows = (n + cols - 1) // cols
    fig = Figure(figsize=(4.2 * cols, 3.0 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    for k, (name, pts) in enumerate(sorted(params.items())):
        ax = fig.add_subplot(rows, cols, k + 1)
        ax.plot([p["cumulative_cycles"] for p in pts], [p["value"] for p in pts], "o-")
        unit = pts[-1]["unit"]
        ax.set_title(f"{name}" + (f" [{unit}]" if unit and unit != "1" else ""), fontsize=9)
        ax.set_xlabel("cumulative high-voltage cycles")
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"specimen {specimen}: fitted parameters over its life")
    out.parent.mkdir(parents=True, exist_ok=True)
    from bench.storage.outputs import atomic_output

    with atomic_output(out, replace=True) as tmp:  # whole or not at all
        fig.savefig(tmp, dpi=110)
    return out
