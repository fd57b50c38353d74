"""The subcommands of ``backpack-slam``: one module per command (see ``backpack_slam.cli``)."""

import argparse
from pathlib import Path


def output_path(text: str) -> Path:
    """An ``--out`` value: a path whose last part names the file or folder to write (``''``,
    ``.``, ``..`` and ``/`` name none: the output is written beside its target under a temporary
    name, then renamed)."""
    path = Path(text)
    if path.name in ("", "..") or not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r} names no file or folder to write")
    return path


def input_file(text: str) -> str:
    """A value naming a file to read (or a rig by name): not empty (``''`` is the current folder
    to the readers, whose error then names no option)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"{text!r} names no file")
    return text
