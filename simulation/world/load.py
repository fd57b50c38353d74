"""Find and load world descriptions: a name looks up ``<configs>/worlds/<name>.yaml``."""

from __future__ import annotations

from pathlib import Path

from common.config import config_names, load, resolve_config
from simulation.world.compile import compile_world
from simulation.world.model import World
from simulation.world.spec import WorldSpec


def world_names() -> list[str]:
    """Names of the ready worlds in ``configs/worlds/``."""
    return config_names("worlds")


def resolve_world(name_or_path: str | Path) -> Path:
    """A world name or a YAML path -> the file; a ConfigError names what is missing."""
    return resolve_config("worlds", name_or_path)


def load_world(name_or_path: str | Path) -> World:
    """Load, validate and compile a world by name (``configs/worlds/<name>.yaml``) or path."""
    path = resolve_world(name_or_path)
    spec = load(WorldSpec, path)
    return compile_world(spec, str(path))
