"""What users hand in, read and checked before anything compiles: input files and numbers.

Every loader (robot, scenario, gains, perturbation ranges, realism) reads its file with
[`read_document()`][spacegrasp_jax.core.inputs.read_document] and checks its numbers with [`numbers()`][spacegrasp_jax.core.inputs.numbers], so every input fails the
same way: a ``ValueError`` subclass of the loader's own (``ScenarioError``, ``GainsError``,
...) whose one-line message names the file and the key.

Strict means: a file must be UTF-8 text parsing to a table (a JSON object or a TOML
document), and a number must be written as a number: ``true`` and ``"1.5"`` are refused
rather than read as 1 and 1.5.
"""

from __future__ import annotations

import difflib
import json
import sys
import tomllib
from pathlib import Path

import jax
import numpy as np


def read_text(path: str | Path, error: type[ValueError]) -> str:
    """The UTF-8 text of the file ``path``.

    Raises:
        error: ``path`` is missing, a folder, unreadable, or not UTF-8 text (a binary file).
    """
    path = Path(path)
    try:
        if path.is_dir():
            raise error(f"{path}: is a folder, not a file")
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not UTF-8 text (a binary file?)") from None
    except OSError as failure:
        raise error(f"{path}: cannot read ({failure.strerror or failure})") from None


def parse_document(text: str, file_format: str, source: str, error: type[ValueError]) -> dict:
    """``text`` parsed as ``file_format`` (``"json"`` or ``"toml"``), which must give a table.

    Raises:
        error: not valid JSON/TOML, nested too deeply, or its top level is not a table
            (a JSON list, number or ``null``); the message names ``source``.
    """
    name = file_format.upper()
    try:
        document = json.loads(text) if file_format == "json" else tomllib.loads(text)
    except RecursionError:
        raise error(f"{source}: nested too deeply to be a {name} settings file") from None
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as failure:
        raise error(f"{source}: not valid {name}: {failure}") from None
    if not isinstance(document, dict):
        kind = "null" if document is None else type(document).__name__
        raise error(f"{source}: expected a {name} object of settings at the top level, got {kind}")
    return document


def read_document(path: str | Path, error: type[ValueError], file_format: str | None = None) -> dict:
    """The table in the file ``path``: JSON or TOML as ``file_format`` says, or by the
    file's extension (``.json``: JSON, anything else TOML) when it is ``None``.

    Raises:
        error: see [`read_text()`][spacegrasp_jax.core.inputs.read_text] and [`parse_document()`][spacegrasp_jax.core.inputs.parse_document].
    """
    path = Path(path)
    file_format = file_format or ("json" if path.suffix.lower() == ".json" else "toml")
    return parse_document(read_text(path, error), file_format, str(path), error)


def numbers(value, where: str, error: type[ValueError], allow_infinite: bool = False) -> np.ndarray:
    """``value`` (a number, nested lists of numbers, or a numeric array) as a finite float64
    array (``allow_infinite``: or infinite, never NaN). Booleans, strings, ``None`` and ragged
    lists are refused, naming ``where``.

    Raises:
        error: not numbers, not rectangular, or not finite.
    """
    if isinstance(value, (np.ndarray, np.generic, jax.Array)):
        if np.asarray(value).dtype.kind not in "iuf":
            raise error(f"{where}: expected numbers, got an array of {np.asarray(value).dtype}")
    else:
        pending = [value]
        while pending:  # iterative: a deeply nested list must not overflow the stack
            item = pending.pop()
            if isinstance(item, (list, tuple)):
                pending.extend(item)
            elif isinstance(item, bool) or not isinstance(item, (int, float, np.integer, np.floating)):
                raise error(f"{where}: expected numbers, got {short(value)}")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (ValueError, OverflowError):
        raise error(f"{where}: expected a rectangular array of numbers, got {short(value)}") from None
    if np.any(np.isnan(array)) or not (allow_infinite or np.all(np.isfinite(array))):
        raise error(
            f"{where}: must be {'a number (not NaN)' if allow_infinite else 'finite'}, got {short(array.tolist())}"
        )
    return array


def is_real(value) -> bool:
    """Whether ``value`` is a finite real number as a file writes one: an int or a float (not
    a bool) within float64's range (``10**400`` is not)."""
    return not isinstance(value, bool) and isinstance(value, (int, float)) and abs(value) <= sys.float_info.max


def short(value, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters for an error message."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


__all__ = ["is_real", "numbers", "parse_document", "read_document", "read_text", "short"]


def did_you_mean(name: str, known) -> str:
    """`` (did you mean X?)`` for the known name closest to a mistyped ``name`` (the same
    letters in another case first, then by ``difflib``'s similarity), or ``""`` when none is
    close."""
    known = list(known)
    same_letters = [candidate for candidate in known if candidate.lower() == name.lower()]
    close = same_letters or difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""
