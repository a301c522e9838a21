"""The CLI's rich console: units in brackets stay text, and redirected output is never cut to a terminal width.

* rich reads ``[s]``, ``[mm]``, ``[kV]`` as markup tags (``s`` is even a style: strike) and drops them. Here
  only tags made of style words (``[bold]``, ``[green]``, ``[/]`` …, spelled out) are markup; every other
  bracket is printed as written. Text from files and users is still escaped where it is printed.
* When stdout is not a terminal (``bench report … > file``, pipes, CliRunner), tables and lines are laid out
  as wide as their content (up to :data:`REDIRECTED_WIDTH`) instead of the terminal's 80 columns; ``COLUMNS``
  in the environment still sets the width explicitly.
"""

from __future__ import annotations

import os
import re
from typing import Any

from rich.color import ANSI_COLOR_NAMES
from rich.console import Console, ConsoleDimensions
from rich.text import Text

REDIRECTED_WIDTH = 10_000  # columns when stdout is not a terminal: wide enough for any table the CLI prints

_TAG = re.compile(r"(\\*)\[([a-z#/@][^[]*?)]")
_WORDS = frozenset({"bold", "dim", "italic", "underline", "blink", "reverse", "strike", "not", "on", "default",
                    "none", "overline", "conceal", "frame", "encircle"}) | frozenset(ANSI_COLOR_NAMES)


def _is_style(tag: str) -> bool:
    words = tag.split()
    return bool(words) and all(w in _WORDS or w.startswith("#") for w in words)


def literal_units(markup: str) -> str:
    """``markup`` with every bracket that is not a spelled-out style tag escaped (``[s]`` stays ``[s]``)."""

    def fix(m: re.Match[str]) -> str:
        slashes, tag = m.group(1), m.group(2)
        if len(slashes) % 2:  # already escaped
            return m.group(0)
        inner = tag[1:] if tag.startswith("/") else tag
        if (tag.startswith("/") and not inner) or _is_style(inner):
            return m.group(0)
        return f"{slashes}\\[{tag}]"

    return _TAG.sub(fix, markup)


class BenchConsole(Console):
    """:class:`rich.console.Console` with units kept and full-width output when redirected (see module).

    ``COLUMNS``/``LINES`` are read when the size is asked, not once when the console is made: the console is made
    on first print (fast ``--help``), and a width in the environment at that moment must not stick (it did: a
    redirected ``inspect`` cut its paths at the width some earlier command in the process had been given)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        if kwargs.get("width") is None:
            self._width = None
        if kwargs.get("height") is None:
            self._height = None

    def render_str(self, text: str, **kwargs: Any) -> Text:
        markup = kwargs.get("markup")
        if markup or (markup is None and self._markup):
            text = literal_units(text)
        return super().render_str(text, **kwargs)

    @property
    def size(self) -> ConsoleDimensions:
        dims = super().size
        if self._width is None and not self.is_terminal and not os.environ.get("COLUMNS", "").isdigit():
            return ConsoleDimensions(REDIRECTED_WIDTH, dims.height)
        return dims

    @size.setter
    def size(self, new_size: tuple[int, int]) -> None:
        self._width, self._height = new_size
