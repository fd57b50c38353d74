"""Find and load world descriptions: a name looks up ``<configs>/worlds/<name>.yaml``."""

from __future__ import annotations

import os
from pathlib import Path

from backpack_slam.config import ConfigError, load
from simulation.world.compile import compile_world
from simulation.world.model import World
from simulation.world.spec import WorldSpec

#: Environment variable naming the configs folder (holding ``worlds/``).
CONFIGS_ENV = "BACKPACK_SLAM_CONFIGS"


def configs_dir() -> Path:
    """The configs folder: ``$BACKPACK_SLAM_CONFIGS`` or ``configs/`` at the repository root."""
    env = os.environ.get(CONFIGS_ENV)
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "configs"


def world_names() -> list[str]:
    """Names of the ready worlds in ``configs/worlds/``."""
    return sorted(p.stem for p in (configs_dir() / "worlds").glob("*.yaml"))


def resolve_world(name_or_path: str | Path) -> Path:
    """A world name or a YAML path -> the file; a ConfigError names what is missing."""
    s = str(name_or_path)
    p = Path(s)
    if p.suffix in (".yaml", ".yml") or os.sep in s or p.is_file():
        if not p.is_file():
            raise ConfigError(f"{p}: no such world file")
        return p
    candidate = configs_dir() / "worlds" / f"{s}.yaml"
    if not candidate.is_file():
        known = ", ".join(world_names()) or "none"
        raise ConfigError(f"world {s!r}: no file {candidate} (known worlds: {known})")
    return candidate


def load_world(name_or_path: str | Path) -> World:
    """Load, validate and compile a world by name (``configs/worlds/<name>.yaml``) or path."""
    path = resolve_world(name_or_path)
    spec = load(WorldSpec, path)
    return compile_world(spec, str(path))
