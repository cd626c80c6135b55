"""Errors that the command line turns into exit status 2 with one line on stderr."""

from __future__ import annotations


class InputError(Exception):
    """Bad input: names the file, the line and/or column, and what is wrong.

    str(err) is the one-line message printed by `magcal` (exit status 2), e.g.
    ``data.csv:17: column 'mmc1_set_x': non-numeric value 'abc'``.
    """

    def __init__(self, path, message, line=None, column=None):
        self.path = str(path) if path is not None else None
        self.line = line
        self.column = column
        self.message = message
        super().__init__(self.format())

    def format(self) -> str:
        where = self.path or "<input>"
        if self.line is not None:
            where += f":{self.line}"
        col = f"column '{self.column}': " if self.column is not None else ""
        return f"{where}: {col}{self.message}"
