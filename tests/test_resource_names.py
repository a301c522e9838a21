"""Shipped protocols and rigs are found by their listed name or an unambiguous base name (issue 26 item 8)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bench.resources import _pick, protocol


@pytest.mark.parametrize("name", ["short/thesis-identification-short", "thesis-identification-short",
                                  "thesis-identification-short.toml",
                                  "protocols/short/thesis-identification-short.toml"])
def test_a_protocol_is_found_by_its_base_name_or_path(name: str) -> None:
    found = protocol(name)
    assert found.name == "thesis-identification-short.toml" and found.parent.name == "short"


def test_an_ambiguous_base_name_names_every_match_and_an_unknown_one_the_choices() -> None:
    known = {"a/run": Path("a/run.toml"), "b/run": Path("b/run.toml"), "other": Path("other.toml")}
    with pytest.raises(ValueError, match=r"shipped protocol 'run' is ambiguous: a/run, b/run"):
        _pick(known, "run", "protocol")
    assert _pick(known, "b/run.toml", "protocol") == Path("b/run.toml")
    with pytest.raises(ValueError, match=r"no shipped protocol 'nope': one of a/run, b/run, other"):
        _pick(known, "nope", "protocol")
