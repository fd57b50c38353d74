"""``backpack-slam view``: open a run's ``map.rrd`` in the rerun viewer."""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

DESCRIPTION = """Open DIR/map.rrd (or an .rrd file) in the rerun viewer shipped with rerun-sdk.
Without a display (no DISPLAY or WAYLAND_DISPLAY), print the command to run instead."""


class ViewError(ValueError):
    """Nothing to view."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "view", help="open a run's map.rrd in the rerun viewer", description=DESCRIPTION
    )
    p.add_argument("dir", type=Path, metavar="DIR", help="SLAM output folder (or a .rrd file)")
    p.add_argument(
        "--print", action="store_true", dest="print_only", help="only print the viewer command"
    )
    return p


def recording_path(target: Path) -> Path:
    """The ``.rrd`` to open for ``target`` (a run folder or a file)."""
    rrd = target / "map.rrd" if target.is_dir() else target
    if not rrd.is_file():
        raise ViewError(f"{rrd}: no such recording")
    return rrd


def rerun_executable() -> str:
    """The ``rerun`` viewer beside this Python (the venv's, matching the SDK), else on PATH."""
    exe = Path(sys.executable).with_name("rerun")
    if exe.is_file():
        return str(exe)
    found = shutil.which("rerun")
    if found is None:
        raise ViewError("rerun: viewer executable not found (pip install rerun-sdk==0.41.0)")
    return found


def has_display(environ: Any = None) -> bool:
    """Whether a viewer window can open: always on macOS/Windows, else needs X11 or Wayland."""
    env = os.environ if environ is None else environ
    if not sys.platform.startswith("linux"):
        return True
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


def run(args: argparse.Namespace) -> int:
    rrd = recording_path(args.dir)
    cmd = [rerun_executable(), str(rrd)]
    if args.print_only or not has_display():
        if not args.print_only:
            print("no display (DISPLAY/WAYLAND_DISPLAY unset); open the map with:")
        print(shlex.join(cmd))
        return 0
    return subprocess.call(cmd)
