"""The offline-model use cases refuse a choice they do not know, in one line naming it (they used to fall through
to the last configuration, or pass the string on to the model)."""

import pytest

from bench.app.simulate import simulate_lsdea, simulate_thesis


def test_an_unknown_lsdea_test_is_refused_not_run_as_isotonic() -> None:
    with pytest.raises(ValueError, match=r"^test must be one of isopotential, isometric, isotonic, got 'isobaric'$"):
        simulate_lsdea("isobaric", 1, 1000.0)


@pytest.mark.parametrize(("kwargs", "what"), [({"method": "euler"}, "--method"), ({"waveform": "saw"}, "waveform"),
                                              ({"electrostriction": "both"}, "electrostriction")])
def test_an_unknown_thesis_choice_is_refused_by_name(kwargs: dict[str, str], what: str) -> None:
    with pytest.raises(ValueError, match=f"^{what} must be one of "):
        simulate_thesis(1000.0, 1.0, 296.0, 1.0, **kwargs)
