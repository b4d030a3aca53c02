"""What several commands share: `NAME=VALUE` options (`--fix`, `--bound`) that may be repeated or
list several assignments without swallowing the positional files after them, and the library's
`progress` argument from `-q/--quiet`."""

from __future__ import annotations

import argparse
from pathlib import Path


def split_top_level(text: str) -> list[str]:
    """`text` cut at its commas outside brackets: `"m=2.5,I[0,0]=1e-3"` -> `["m=2.5", "I[0,0]=1e-3"]`
    (a JSON list keeps its commas: `"r_m=[0,0,-0.02]"` is one item)."""
    items, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        if ch in "[(":
            depth += 1
        elif ch in "])":
            depth -= 1
        elif ch == "," and depth == 0:
            items.append(text[start:i])
            start = i + 1
    items.append(text[start:])
    return [item.strip() for item in items if item.strip()]


def _is_assignment(value: str) -> bool:
    """Whether `value` reads as NAME=VALUE rather than a file (an existing path is a file)."""
    name = value.partition("=")[0]
    return "=" in value and bool(name.strip()) and not Path(value).exists()


class Assignments(argparse.Action):
    """`--fix NAME=VALUE`, repeatable, each value possibly a comma-separated list
    (`--fix m=2.5,j=1e-4`), and several after one option (`--fix m=2.5 m0=0.8`). The first value
    after the option is always an assignment (a wrong one is reported as such); from the first
    later value that is not `NAME=VALUE` on, the values are the command's positional files, which
    go to `spill` (`--fix m=2.5 trial.csv` leaves `trial.csv` to the files)."""

    def __init__(self, option_strings, dest, spill: str, **kwargs):
        self.spill = spill
        super().__init__(option_strings, dest, nargs="+", **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        got = list(getattr(namespace, self.dest, None) or [])
        files = list(getattr(namespace, self.spill, None) or [])
        for i, value in enumerate(values):
            if files or (i and not _is_assignment(value)):
                files.append(value)
            else:
                got += split_top_level(value) or [value]
        setattr(namespace, self.dest, got)
        setattr(namespace, self.spill, files)


def progress(args) -> bool | None:
    """The `progress` argument of the library for a command: bars where stderr is a terminal
    (lines through the `jsphere` logger elsewhere), none with `--quiet`."""
    return False if args.quiet else None
