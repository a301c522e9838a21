"""CLI commands on the run catalogue: runs list, specimen show, catalog rebuild (heavy imports inside each)."""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, NoReturn, ParamSpec, TypeVar

import typer

from bench.cli.common import JsonOpt, Table, clean_errors, console, escape, print_json
from bench.numbers import mv_per_m

CatalogOpt = Annotated[str | None, typer.Option(
    "--catalog", metavar="URL", help="Catalogue database URL (default: $BENCH_CATALOG, else DIR/catalog.sqlite), "
    "e.g. postgresql+psycopg://lab@server/bench for a lab's shared server.")]
DirOpt = Annotated[Path, typer.Option("--dir", help="The lab's runs folder (reconciled with the catalogue first); only "
                                      "its files are shown, each run once.")]
EverywhereOpt = Annotated[bool, typer.Option(
    "--everywhere", help="Also the catalogue's runs outside --dir (this host's: if their file still exists) and of "
    "other hosts sharing it (as last catalogued there).")]


P = ParamSpec("P")
R = TypeVar("R")


def _db_errors(fn: Callable[P, R]) -> Callable[P, R]:
    """A database that refuses or does not answer: one line (``clean_errors`` prints it), never a traceback."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return fn(*args, **kwargs)
        except Exception as exc:
            if not type(exc).__module__.startswith("sqlalchemy"):
                raise
            from bench.storage.catalog import catalog_url, db_reason

            try:  # which catalogue (an outside tester: "run catalogue: file is not a database" named none)
                folder, given = kwargs.get("folder"), kwargs.get("catalog")
                where = " " + sa_display(catalog_url(folder if isinstance(folder, str | Path) else Path("runs"),
                                                     given if isinstance(given, str) else None))
            except Exception:
                where = ""
            raise ValueError(f"run catalogue{where}: " + db_reason(exc)) from None

    return wrapper


def sa_display(url: str) -> str:
    """A database URL as said in a line: its password hidden."""
    from bench.storage.catalog import sa_display as display

    return display(url)


NO_FIT_PLOT = "no fitted parameters: no plot"  # specimen show on a specimen whose runs hold no fit
RUN_STATES = ("completed", "running", "interrupted", "tripped", "error")  # a run file's /status/state
# and --state paused (a run under way held by `bench pause`) and ended (a file that says running whose writer is gone:
# crashed or killed, or ended unstamped, a full disk), which --state running leaves out (a reviewer: none selected them)
FILTER_STATES = (*RUN_STATES, "paused", "ended")


def _refuse_folder(folder: Path, why: str = "") -> NoReturn:
    """ValueError (one line): ``folder`` is no runs folder — not there (``why``), or a file."""
    from bench.storage.absent import absent_runs_folder

    raise ValueError(absent_runs_folder(folder, why))


def _nothing_to_keep(folder: Path, url: str) -> bool:
    """Whether a listing of ``folder`` would make a SQLite catalogue that holds nothing: none there yet and no run
    file to catalogue (`runs list` in an empty folder left a catalog.sqlite behind, outside tester) — then the listing
    is made in memory. Where the first run file comes, the catalogue is made as before."""
    from bench.storage.catalog import run_files

    if not url.startswith("sqlite:///"):
        return False
    database = Path(url.removeprefix("sqlite:///"))
    return not database.exists() and not (folder.is_dir() and any(run_files(folder)))


def _open(folder: Path, url: str | None, notes: list[str]) -> tuple[Any, set[str]]:
    """The catalogue, reconciled with the run files of ``folder`` (a missing folder: nothing to reconcile), and the
    rows' paths of the files found there (a file linked into it among them); what the reconciliation found worth
    saying is added to ``notes``."""
    from bench.storage.catalog import (
        Catalog,
        CatalogNotWrittenError,
        catalog_url,
        damaged_file,
        db_reason,
        memory_copy,
        reconcile,
        write_refused,
    )

    if folder.is_file():  # a run file given for its folder: the catalogue would be made inside a file
        _refuse_folder(folder)
    url = catalog_url(folder, url)
    try:
        cat = Catalog("sqlite://" if _nothing_to_keep(folder, url) else url)
    except Exception as exc:  # none there yet on a read-only or full medium: made in memory, if SQLite
        if (damaged := damaged_file(exc, url)) is not None:  # listed from the files: the catalogue is only an index
            cat = Catalog("sqlite://")
            notes.append(f"[yellow]run catalogue {escape(str(damaged))} is damaged ({escape(db_reason(exc))})[/]: "
                         f"listed from the files; `bench catalog rebuild {escape(str(folder))}` sets it aside and "
                         "makes a new one")
        elif (why := write_refused(exc)) is None or (copy := memory_copy(url)) is None:
            raise
        else:
            cat = copy
            notes.append(f"[yellow]run catalogue {escape(url)} cannot be written ({escape(why)})[/]: listed from "
                         "the files; the catalogue itself is not updated")
    if not folder.is_dir():
        return cat, set()
    try:
        done = reconcile(cat, folder)
    except CatalogNotWrittenError as exc:  # a listing is a read: the files are read, the update that failed is let go
        shown = escape(cat.display)
        if (copy := memory_copy(cat.url)) is None:  # a shared server: its rows as they are
            notes.append(f"[yellow]run catalogue {shown} cannot be written ({escape(exc.why)})[/]: the listing may "
                         "be stale (its rows as last written)")
            done = exc.done
        else:
            cat.close()
            cat = copy
            notes.append(f"[yellow]run catalogue {shown} cannot be written ({escape(exc.why)})[/]: listed from the "
                         "files; the catalogue itself is not updated")
            try:
                done = reconcile(cat, folder)
            except BaseException:
                cat.close()
                raise
    except BaseException:
        cat.close()
        raise
    notes.extend(f"[yellow]not a readable run file[/]: {escape(line)}" for line in done.unreadable or [])
    if done.removed:
        notes.append(f"{done.removed} catalogued file(s) no longer in {escape(str(folder))}: their rows removed")
    return cat, done.found


def _select(cat: Any, folder: Path, found: set[str], everywhere: bool, notes: list[str],
            **filters: Any) -> list[dict[str, Any]]:
    """The catalogue's rows (``filters``: :meth:`~bench.storage.catalog.Catalog.rows`) of the files in ``folder`` on
    this host — just reconciled, so each file exists; ``found``: their paths, a file linked into the folder counted
    in it — one per run (copies of a run, the same run ID, count once: :func:`~bench.storage.catalog.one_per_run`).
    ``everywhere``: also rows of this host's other folders whose file still exists, and other hosts' rows as they
    were last catalogued (their files cannot be checked here)."""
    from bench.storage.catalog import host_name, in_folder, one_per_run

    host, inside = host_name(), in_folder(folder, found=found)
    kept, outside, gone, foreign = [], 0, 0, 0
    for r in cat.rows(**filters):
        if inside(r):
            kept.append(r)
        elif not everywhere:
            outside += 1
        elif r["host"] != host:
            kept.append(r)
            foreign += 1
        elif Path(r["path"]).is_file():
            kept.append(r)
        else:
            gone += 1
    rows = one_per_run(kept, prefer=folder, found=found)
    where = escape(str(folder))
    if outside:
        notes.append(f"{outside} catalogued file(s) outside {where} or on other hosts not shown (--everywhere)")
    if gone:
        notes.append(f"{gone} catalogued file(s) outside {where} no longer exist: not counted (`bench catalog rebuild "
                     "THEIR-FOLDER` removes their rows)")
    if foreign:
        notes.append(f"{foreign} file(s) of other hosts as last catalogued there (not checked from here)")
    copies = [r for r in rows if r["copies"]]
    if copies:
        n = sum(len(r["copies"]) for r in copies)
        shown = "; ".join(f"{escape(r['path'])} = " + ", ".join(escape(c) for c in r["copies"]) for r in copies[:3])
        notes.append(f"{n} file(s) are copies of a run shown (the same run ID, counted once; the copy in {where} "
                     f"shown): {shown}" + (f"; and {len(copies) - 3} more run(s) (--json: copies)"
                                           if len(copies) > 3 else ""))
    return rows


def _notes(notes: list[str], json_out: bool) -> None:
    """What the listing left out or counted once: on stdout, or on stderr where stdout holds the JSON."""
    from bench.cli.common import err_console

    for line in notes:
        (err_console if json_out else console).print(line, soft_wrap=True, highlight=False)


def _since(text: str) -> str:
    """``--since`` (a date or date-time, local time unless it names a zone) as the catalogue's UTC stamp."""
    try:
        when = datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"--since: {text!r} is not a date (YYYY-MM-DD) or date-time (YYYY-MM-DDTHH:MM)") from None
    return when.astimezone(UTC).isoformat(timespec="milliseconds")


def plot_name(specimen: str) -> str:
    """The default name of a specimen's plot: ``specimen-<ID>.png``, the ID's characters other than letters, digits,
    ``_.-`` replaced by ``-`` — and where that changed it (or cut it to 100), a short hash of the exact ID added, so
    two specimens never share a plot (``a b`` and ``a/b`` both gave ``specimen-a-b.png``, the second overwriting the
    first)."""
    import hashlib

    safe = re.sub(r"[^A-Za-z0-9_.-]+", "-", specimen)
    if safe == specimen and len(safe) <= 100:
        return f"specimen-{safe}.png"
    return f"specimen-{safe[:100]}-{hashlib.sha256(specimen.encode()).hexdigest()[:8]}.png"


def _hours(s: float | None) -> str:
    if s is None:
        return "–"
    return f"{s:.1f} s" if s < 60 else f"{s / 60:.1f} min" if s < 3600 else f"{s / 3600:.2f} h"


@clean_errors
@_db_errors
def runs_list(
    folder: DirOpt = Path("runs"),
    specimen: Annotated[str | None, typer.Option("--specimen", help="Only this specimen ID.")] = None,
    protocol: Annotated[str | None, typer.Option("--protocol", help="Only this protocol name.")] = None,
    since: Annotated[str | None, typer.Option("--since", help="Only runs started at or after this date "
                                              "(YYYY-MM-DD[THH:MM], local time).")] = None,
    state: Annotated[str | None, typer.Option("--state", help="Only runs in this state (completed, running, "
                                              "interrupted, tripped, error; paused: under way, held by "
                                              "`bench pause`; ended: crashed, killed or not stamped, e.g. a full "
                                              "disk).")] = None,
    everywhere: EverywhereOpt = False,
    catalog: CatalogOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """List the catalogued runs of --dir (one row per run; copies of a run file counted once), after reconciling
    the catalogue with the files."""
    cutoff = _since(since) if since is not None else None
    if state is not None and state not in FILTER_STATES:
        raise ValueError(f"--state: {state!r} is not a run state ({', '.join(FILTER_STATES)})")
    if catalog is None and not folder.is_dir():  # its catalogue would be made there: a typo made a new lab folder
        _refuse_folder(folder, " (no run recorded there yet, or --dir misspelt?)")
    notes: list[str] = []
    cat, found = _open(folder, catalog, notes)
    with cat:
        rows = _select(cat, folder, found, everywhere, notes, specimen=specimen, protocol=protocol, since=cutoff,
                       state=state)
    _notes(notes, json_out)
    _print_runs(rows, json_out)


def _print_runs(rows: list[dict[str, Any]], json_out: bool) -> None:
    """The listed rows: JSON (each with ``state_shown``, the state as the table shows it), or the table."""
    import json

    from bench.storage.catalog import shown_state

    if json_out:
        print_json([{**r, "state_shown": shown_state(r), "figures": json.loads(r["figures"] or "[]"),
                     "fits": json.loads(r["fits"] or "[]"), "signature": None} for r in rows])
        return
    t = Table(title=f"runs ({len(rows)})")
    for col in ("started (UTC)", "file", "protocol", "specimen", "operator", "state", "steps", "HV time", "fits"):
        t.add_column(col)
    for r in rows:
        state_txt = shown_state(r) if r["complete"] else f"[red]{shown_state(r)}, incomplete[/]"
        t.add_row(str(r["start_time"] or "")[:19], escape(Path(r["path"]).name), escape(r["protocol_name"] or ""),
                  escape(r["specimen_id"] or ""), escape(r["operator"] or ""), state_txt,
                  f"{r['steps_completed'] or 0}/{r['steps_total'] or 0}", _hours(r["hv_time_s"]),
                  str(len(json.loads(r["fits"] or "[]"))))
    console.print(t)


def _history_table(specimen: str, h: dict[str, Any]) -> Any:
    """A specimen's runs in order (``bench specimen show``)."""
    t = Table(title=f"specimen {specimen}: {len(h['runs'])} run(s)")
    for col in ("started (UTC)", "file", "protocol", "state", "steps", "HV time", "cycles", "Σ HV time", "Σ cycles",
                "max E nominal [MV/m]", "max E true [MV/m]"):
        t.add_column(col)
    for r in h["runs"]:
        field = r["max_nominal_field_V_per_m"]
        t.add_row(str(r["start_time"] or "")[:19], escape(Path(r["file"]).name), escape(r["protocol"] or ""),
                  r["state_shown"] if r["complete"] else f"[red]{r['state_shown']}, incomplete[/]", r["steps"],
                  _hours(r["hv_time_s"]), str(r["hv_cycles"] or 0), _hours(r["cumulative_hv_time_s"]),
                  str(r["cumulative_cycles"]), "–" if field is None else f"{field / 1e6:.2f}",
                  "–" if r["max_true_field_V_per_m"] is None else f"{r['max_true_field_V_per_m'] / 1e6:.2f}")
    return t


def _plot(h: dict[str, Any], specimen: str, folder: Path, plot: Path | None, json_out: bool) -> Path | None:
    """The specimen's parameter plot (``plot``, default beside the runs); a default that cannot be written (a
    read-only or full medium) is skipped, said in one line: the history is still shown."""
    from bench.storage.catalog import plot_history

    try:
        return plot_history(h, specimen, plot if plot is not None else folder / plot_name(specimen))
    except OSError as exc:
        if plot is not None:  # asked for: its failure is the command's
            raise
        _notes([f"[yellow]plot not written[/] ({escape(' '.join(str(exc).split()))}): give --plot elsewhere"],
               json_out)
        return None


def _field_line(h: dict[str, Any]) -> str:
    """The specimen's highest fields, like with like: the true field (Vλ²/L3, λ from the recorded laser) against
    the model's breakdown field, a true-field limit; the nominal field (|V| over the unstretched thickness) only
    named, never divided by it."""
    nominal = (f"highest nominal field (|V| / unstretched thickness): {h['max_nominal_field_V_per_m'] / 1e6:.2f} "
               "MV/m")
    e_b = h["breakdown_field_V_per_m"]
    if h["max_true_field_V_per_m"] is None:
        return nominal + ("" if e_b is None else f"; true field not known from the records (no laser or aperture "
                          f"record), so not compared with the breakdown field {mv_per_m(e_b)} MV/m (a true-field "
                          "limit)")
    if h.get("stretch_dependent_breakdown"):  # LS-DEA: E_B = E0 λ3^(−r/2) grows with the stretch
        true = (f"highest true field (|V|λ1λ2/t0, the stretch from the recorded aperture): "
                f"{h['max_true_field_V_per_m'] / 1e6:.2f} MV/m")
        if h["field_ratio"] is not None:
            true += (f"; at most {h['field_ratio']:.3f} × the breakdown field at the same stretch (E0 λ3^(−r/2), "
                     f"E0 = {mv_per_m(e_b)} MV/m)")
        return f"{true}; {nominal}"
    true = f"highest true field (|V|λ²/L3, λ from the recorded laser): {h['max_true_field_V_per_m'] / 1e6:.2f} MV/m"
    if h["field_ratio"] is not None:
        true += f" = {h['field_ratio']:.3f} × the model's breakdown field {mv_per_m(e_b)} MV/m"
    return f"{true}; {nominal}"


@clean_errors
@_db_errors
def specimen_show(
    specimen: Annotated[str, typer.Argument(help="Specimen ID (as given by --specimen-id or the protocol).")],
    folder: DirOpt = Path("runs"),
    plot: Annotated[Path | None, typer.Option(
        "--plot", help="PNG of each fitted parameter vs cumulative cycles (default: DIR/specimen-<ID>.png, a hash of "
        "the ID added where its characters were replaced).")] = None,
    everywhere: EverywhereOpt = False,
    catalog: CatalogOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """A specimen's life: its runs in order, time under high voltage, cycles, highest true field (from the recorded
    stretch) against the model's breakdown field and highest nominal field, failures, and each fitted parameter over
    its cycles (with a plot)."""
    from bench.storage.catalog import specimen_history

    notes: list[str] = []
    cat, found = _open(folder, catalog, notes)
    with cat:
        rows = _select(cat, folder, found, everywhere, notes, specimen=specimen)
    _notes(notes, json_out)
    if not rows:
        raise ValueError(f"specimen {specimen!r}: no catalogued run (runs folder {folder}; `bench runs list`)")
    h = specimen_history(rows)
    png = _plot(h, specimen, folder, plot, json_out)
    h["plot"] = str(png) if png is not None else None
    if json_out:
        print_json({"specimen": specimen, **h})
        return
    console.print(_history_table(specimen, h))
    console.print(f"time under high voltage (measured |V| > {h['hv_threshold_V']:g} V): {_hours(h['hv_time_s'])} "
                  f"({h['hv_time_s']:.3f} s); high-voltage cycles: {h['hv_cycles']}")
    if h["max_nominal_field_V_per_m"] is not None:
        console.print(_field_line(h), soft_wrap=True)
    for f in h["failures"]:
        console.print(f"[red]failed / not finished[/]: {escape(Path(f['file']).name)} ({f['state_shown']}): "
                      f"{escape(str(f['reason']))}", soft_wrap=True)
    for name, pts in sorted(h["parameters"].items()):
        console.print(f"{escape(name)}: " + ", ".join(f"{p['value']:.5g} at {p['cumulative_cycles']} cycles"
                                                      for p in pts), soft_wrap=True)
    if h["fits_across_specimens"]:
        console.print(f"[yellow]{h['fits_across_specimens']} fit(s) across several specimens[/] (bench fit warned): "
                      "left out of the parameters' history")
    console.print(f"plot: {escape(str(png))}" if png else ("no plot" if h["parameters"] else NO_FIT_PLOT))


@clean_errors
@_db_errors
def catalog_rebuild(
    folder: Annotated[Path, typer.Argument(help="The runs folder to rebuild the catalogue from.")],
    catalog: CatalogOpt = None,
    json_out: JsonOpt = False,
) -> None:
    """Rebuild the catalogue's rows of a runs folder from the run files (the files are the source of truth). A
    damaged SQLite catalogue (not a database, a malformed image) is set aside (``catalog.sqlite.damaged-<time>``)
    and made again."""
    from bench.storage.catalog import Catalog, catalog_url, damaged_file, db_reason, reconcile, set_aside

    if not folder.is_dir():
        _refuse_folder(folder, " (nothing to rebuild the catalogue from)")
    url, moved = catalog_url(folder, catalog), None
    for attempt in range(2):
        try:
            with Catalog(url) as cat:
                done = reconcile(cat, folder, rebuild=True)
                prefix = str(folder.resolve()).rstrip("/") + "/"
                n = len(cat.rows(under=folder.resolve())) + sum(not k.startswith(prefix) for k in done.found)
            break
        except Exception as exc:  # (a damaged file found by the first try only: the second is a new one)
            if attempt or (damaged := damaged_file(exc, url)) is None:
                raise
            moved = (damaged, set_aside(damaged), db_reason(exc))
    if json_out:
        print_json({"catalog": cat.display, "rows": n, "removed": done.removed, "unreadable": done.unreadable,
                    "set_aside": str(moved[1]) if moved else None})
        return
    if moved:
        console.print(f"[yellow]catalogue {escape(str(moved[0]))} was damaged[/] ({escape(moved[2])}): set aside as "
                      f"{escape(str(moved[1]))}", soft_wrap=True)
    for line in done.unreadable or []:
        console.print(f"[yellow]not a readable run file[/]: {escape(line)}", soft_wrap=True)
    console.print(f"catalogue {escape(cat.display)} rebuilt from {escape(str(folder))}: {n} run file(s)"
                  + (f", {done.removed} row(s) of missing files removed" if done.removed else ""))


def register(app: typer.Typer) -> None:
    """Put ``runs list``, ``specimen show`` and ``catalog rebuild`` on ``app``."""
    groups = {name: typer.Typer(help=text, no_args_is_help=True, rich_markup_mode=None) for name, text in (
        ("runs", "The run catalogue: every run file of the lab, searchable."),
        ("specimen", "A specimen's life over its runs (from the run catalogue)."),
        ("catalog", "The run catalogue itself (SQLite beside the runs, or a shared PostgreSQL server)."))}
    for name, sub in groups.items():
        app.add_typer(sub, name=name)
    groups["runs"].command("list")(runs_list)
    groups["specimen"].command("show")(specimen_show)
    groups["catalog"].command("rebuild")(catalog_rebuild)
