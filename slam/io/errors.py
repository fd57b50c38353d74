"""The readers' error type: one line naming the input (file, topic) and what is wrong."""

from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """An input file (or a topic in it) that cannot be read; the message names it."""


def input_error(path: str | Path, what: str, topic: str | None = None) -> InputError:
    """``InputError("<path>[ topic <topic>]: <what>")`` on one line."""
    where = f"{path}" if topic is None else f"{path} topic {topic}"
    return InputError(f"{where}: {' '.join(str(what).split())}")
