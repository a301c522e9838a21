"""What a host starved of CPU does to a wall-clock run (CI beside a CPU hog): the trips and ends a test that needs
a run still going takes as its premise lost (skipped or tried again), never as a pass."""

from __future__ import annotations

from bench.storage.runfile import RunFile

LOAD_TRIPS = ("stream-out underrun", "host stall")  # what a host starved of CPU (CI beside a hog) trips, rightly


def load_trip(run: RunFile) -> bool:
    """Whether ``run`` ended on what a host starved of CPU does: tripped on a :data:`LOAD_TRIPS` reason, or ended in
    error with the interlock latched on a host stall (the twin that shares the host answered too late: "no valid
    reply", CI beside a hog, 2026-11-28), or in error on the DAQ twin's missing reply with the rig latched for it
    (its stream stop unanswered, the 0 V not read back: CI beside a hog and a browser, the same day), or without
    a latch where the shutdown then verified 0 V (CI beside a hog and a browser, 2026-11-28: the page's address
    refused, the run over at 4.8 s)."""
    if run.state == "tripped":
        return any(k in run.reason for k in LOAD_TRIPS)
    latches = [e[3] for e in run.event_list() if e[2] == "interlock" and "latched" in e[3]]
    verified = any(e[2] == "safe" and "verified: voltage monitor" in e[3] for e in run.event_list())
    starved_twin = "daq: no valid reply" in run.reason and (
        any("(output not verified)" in t for t in latches) or (not latches and verified))
    return run.state == "error" and (starved_twin or any("(host stall)" in text for text in latches))
