"""Use case: a manual-control session on a rig's instruments (``bench devices control``)."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from bench.runtime.manual import Outcome


@dataclass
class ManualResult:
    """How a session went: its log, the readings' file, each command's outcome, what ended it."""

    log: Path
    data_file: Path | None
    outcomes: list[Outcome]
    end_reason: str | None
    safe_path: str = ""  # how the session's end made the output safe (0 V commanded, verified), '' if it did not

    @property
    def not_done(self) -> list[Outcome]:
        """The commands refused, tripped or failed."""
        return [o for o in self.outcomes if o.status != "ok"]

    @property
    def ok(self) -> bool:
        return not self.not_done and not self.end_reason


def command_lines(script: Path | None, interactive: bool, show_help: Callable[[str], None]) -> Iterator[str]:
    """The session's commands: from ``script``, from a prompt with line editing (``interactive``: the help shown
    first), or from stdin."""
    from bench.runtime.manual import HELP, prompt_lines

    if script is not None:
        yield from script.read_text(encoding="utf-8").splitlines()
    elif interactive:
        show_help(HELP)
        yield from prompt_lines("bench> ")
    else:
        yield from iter(sys.stdin.readline, "")


def manual_session(rig_file: Path, *, script: Path | None = None, log: Path | None = None,
                   virtual_time: bool = False, operator: str | None = None, specimen_id: str | None = None,
                   echo: Callable[[str], None], show_help: Callable[[str], None]) -> ManualResult:
    """Run a manual-control session on the rig of ``rig_file`` under the safety supervisor and the latched
    interlock: commands from ``script`` or stdin (a prompt on a terminal), each answer to ``echo``; the session
    log at ``log`` (default runs/manual-<rig>-<time>.log), the readings beside it."""
    from bench.protocol.schema import MAX_OPERATOR, MAX_SPECIMEN_ID, check_label
    from bench.rig import load_rig
    from bench.runtime.manual import ManualSession, session_log_name

    if operator is not None:
        try:
            operator = check_label(operator, MAX_OPERATOR)
        except ValueError as exc:
            raise ValueError(f"--operator: {exc}") from None
    else:  # who acts, as a run records it (outside tester: a reset here recorded "an operator not named")
        from bench.app.runs import login_name

        # no login name (no USER, a uid not in passwd: KeyError) or none that is a valid label: not named, as before
        with contextlib.suppress(ValueError, KeyError, OSError):
            operator = login_name(None)
    if specimen_id is not None:  # the specimen's history counts the session's time at high voltage (an outside
        try:  # tester: a manual session's could not be named)
            specimen_id = check_label(specimen_id, MAX_SPECIMEN_ID)
        except ValueError as exc:
            raise ValueError(f"--specimen-id: {exc}") from None
    if script is not None and (script.is_dir() or not script.exists()):  # before the rig is connected (an outside
        # tester: it connected, then said "[Errno 2]" and left a session file marked error); /dev/null or a named pipe
        # is read as a file is (it was "not found", a later tester)
        raise ValueError(f"--script {script}: " + ("a folder, not a file of commands" if script.is_dir() else
                                                    "not found"))
    rig = load_rig(rig_file)
    path = log if log is not None else Path("runs") / session_log_name(rig)
    interactive = script is None and sys.stdin.isatty()
    session = ManualSession(rig, path, virtual=virtual_time, echo=echo, operator=operator, specimen_id=specimen_id)
    with session.signal_handlers(interactive=interactive), session:
        session.run_lines(command_lines(script, interactive, show_help), stop_on_trip=not interactive)
    return ManualResult(path, session.data_file, session.outcomes, session.end_reason, session.safe_path)
