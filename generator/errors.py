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


class OutputError(Exception):
    """An output that could not be written: the operating system refused the writing (a
    full disk, a quota, a file too large, a read-only or failing filesystem). Not bad
    input and not an internal fault: `magcal` prints str(err), one line naming the output
    and the system's reason, and exits with status 1 (ICD section 3). io.outputs raises it
    after removing what it had begun to write, so no half-written output stays behind.
    """

    def __init__(self, path, reason):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: cannot write the output: {reason}")
