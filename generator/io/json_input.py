"""A JSON document from a file the user gave: every way it can be wrong is InputError."""

from __future__ import annotations

import json
from pathlib import Path

from generator.errors import InputError

# The largest document the toolchain reads (a coefficients.json of 8 sensors with every
# optional stage, a test plan) is a few hundred kB.
MAX_JSON_BYTES = 16 * 2 ** 20


def load_json(path, what: str, max_bytes: int = MAX_JSON_BYTES):
    """The parsed document; InputError naming the file on a missing, unreadable, oversized,
    non-UTF-8, malformed, absurdly nested document or one with a 4300-digit integer.
    what: the kind of file, for the message ("coefficient file", "test plan")."""
    path = Path(path)
    try:
        if path.is_file() and path.stat().st_size > max_bytes:
            raise InputError(path, f"{path.stat().st_size} bytes: larger than any {what} "
                                   f"({max_bytes} bytes at most)")
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"not a JSON {what}: {e}") from None
    except ValueError as e:              # an integer of more than 4300 digits
        raise InputError(path, f"not a {what}: {e}") from None
    except RecursionError:
        raise InputError(path, f"not a {what}: nested too deeply") from None
