"""Atomic outputs: every file or folder is written under a temporary name beside its target and
renamed onto it when complete, so a reader never sees half an output; and strict JSON.

The temporary names start with ``.`` and contain ``.tmp-``; on any exception they are removed
and the target is left as it was.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np


class OutputFileError(ValueError):
    """An output or input file that cannot be read or written; the message names it."""


def temporary_sibling(path: str | Path) -> Path:
    """A fresh hidden name beside ``path`` keeping its suffix (open3d and matplotlib pick the
    format from it)."""
    target = Path(path)
    return target.with_name(f".{target.stem}.tmp-{uuid.uuid4().hex[:12]}{target.suffix}")


def commit(tmp: Path, target: Path) -> None:
    """Rename ``tmp`` (a file or a folder) onto ``target``, replacing a file or a folder there."""
    if target.exists() and target.is_dir() and not target.is_symlink():
        old = target.with_name(f".{target.name}.old-{uuid.uuid4().hex[:8]}")
        os.replace(target, old)
        os.replace(tmp, target)
        shutil.rmtree(old, ignore_errors=True)
        return
    if tmp.is_dir() and target.exists():
        target.unlink()
    os.replace(tmp, target)


def discard(tmp: Path, attempts: int = 20) -> None:
    """Remove a temporary file or folder if it is still there. A folder is tried again (every
    0.1 s, ``attempts`` times) while files still appear in it: a helper process that was writing
    into it when an interrupt arrived may finish its last file after the first removal."""
    if not (tmp.is_dir() and not tmp.is_symlink()):
        tmp.unlink(missing_ok=True)
        return
    for _ in range(attempts):
        shutil.rmtree(tmp, ignore_errors=True)
        if not tmp.exists():
            return
        time.sleep(0.1)


def check_target(target: Path, folder: bool = False) -> None:
    """Refuse targets that renaming would destroy: a device, a link, a folder for a file (and a
    file for a folder); the parent folder must exist."""
    if not target.parent.is_dir():
        raise OutputFileError(f"{target}: folder {target.parent} does not exist")
    if target.is_symlink() or (target.exists() and not (target.is_dir() if folder else target.is_file())):
        kind = "a folder" if folder else "a regular file"
        raise OutputFileError(f"{target}: exists and is not {kind}; not replacing it")


@contextmanager
def atomic_path(path: str | Path, make_parents: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` when the block succeeds.

    With ``make_parents`` the target's folder is created first.
    """
    target = Path(path)
    if make_parents:
        target.parent.mkdir(parents=True, exist_ok=True)
    check_target(target)
    tmp = temporary_sibling(target)
    try:
        yield tmp
        if not tmp.exists():
            raise OutputFileError(f"{target}: nothing was written")
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; it replaces ``path`` (a folder, possibly
    existing) when the block succeeds, and is removed on any exception, leaving ``path`` as it was."""
    target = Path(path)
    if target.exists() and (target.is_symlink() or not target.is_dir()):
        raise OutputFileError(f"{target}: exists and is not a folder; not replacing it")
    tmp = target.with_name(f".{target.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:  # made inside: an interrupt right after the mkdir still removes it
        tmp.mkdir(parents=True)
        yield tmp
        commit(tmp, target)
    except BaseException:
        discard(tmp)
        raise


def write_text(path: str | Path, text: str, make_parents: bool = False) -> Path:
    """Atomically write ``text`` to ``path``."""
    with atomic_path(path, make_parents=make_parents) as tmp:
        tmp.write_text(text)
    return Path(path)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _finite_json(obj: Any) -> Any:
    """Replace non-finite floats by None so the file stays strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite_json(v) for v in obj]
    return obj


def json_text(data: Any, indent: int | None = 2) -> str:
    """Strict JSON of ``data`` (numpy arrays and scalars allowed; non-finite floats -> null)."""
    # Round trip through the encoder first so numpy values become plain floats before the
    # non-finite check.
    plain = _finite_json(json.loads(json.dumps(data, default=_json_default)))
    return json.dumps(plain, indent=indent, allow_nan=False) + "\n"


def write_json(path: str | Path, data: Any, indent: int | None = 2, make_parents: bool = False) -> Path:
    """Atomically write ``data`` as strict JSON."""
    return write_text(path, json_text(data, indent), make_parents=make_parents)


def read_json(path: str | Path) -> Any:
    """Parse a JSON file; a missing or malformed file is an OutputFileError naming it."""
    p = Path(path)
    try:
        return json.loads(p.read_text())
    except OSError as e:
        raise OutputFileError(f"{p}: cannot read ({e.strerror or e})") from None
    except json.JSONDecodeError as e:
        raise OutputFileError(f"{p}: invalid JSON at line {e.lineno}: {e.msg}") from None
