"""YAML configuration validated on load with pydantic.

Every error names the file and the offending key, on one line.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

M = TypeVar("M", bound=BaseModel)


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message names the file and the key."""


class StrictModel(BaseModel):
    """Base of every config section: unknown keys are errors, values are validated, and a float
    must be finite (a NaN or infinite sigma, extrinsic or limit is never meant)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def read_yaml(path: str | Path) -> Any:
    """Parse a YAML file; a missing or malformed file is a ConfigError naming it."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise ConfigError(f"{p}: cannot read ({e.strerror or e})") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: not a text file ({e.reason} at byte {e.start})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{p}: invalid YAML{where}: {getattr(e, 'problem', e)}") from None


def format_validation_error(err: ValidationError, source: str) -> str:
    """One line: file, dotted key and what is wrong (first error, count of the rest)."""
    errs = err.errors()
    # the deepest location first: of a union's alternatives (a scanner model by name or inline),
    # the one that got furthest names the offending key
    first = max(errs, key=lambda e: len(e.get("loc", ())))
    key = ".".join(str(x) for x in first.get("loc", ())) or "(top level)"
    msg = first.get("msg", "invalid")
    if first.get("type") == "extra_forbidden":
        msg = "unknown key"
    more = f" (and {len(errs) - 1} more)" if len(errs) > 1 else ""
    return f"{source}: key '{key}': {msg}{more}"


def validate(model: type[M], data: Any, source: str) -> M:
    """Validate already-parsed data against ``model``; errors name ``source`` and the key."""
    if data is None:
        data = {}
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise ConfigError(format_validation_error(e, source)) from None


def load(model: type[M], path: str | Path) -> M:
    """Read a YAML file and validate it against ``model``."""
    return validate(model, read_yaml(path), str(path))


CONFIGS_ENV = "BACKPACK_SLAM_CONFIGS"

# singular names of the config kinds (folders under ``configs/``) for messages
_SINGULAR = {"worlds": "world", "experiments": "experiment"}


def configs_dir() -> Path:
    """The configs folder: ``$BACKPACK_SLAM_CONFIGS`` or ``configs/`` at the repository root."""
    env = os.environ.get(CONFIGS_ENV)
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[1] / "configs"


def config_names(kind: str) -> list[str]:
    """Names of the ready configurations of ``kind`` (``configs/<kind>/*.yaml``)."""
    return sorted(q.stem for q in (configs_dir() / kind).glob("*.yaml"))


def resolve_config(kind: str, name_or_path: str | Path) -> Path:
    """A name (``configs/<kind>/<name>.yaml``) or a YAML path -> the file; ConfigError if missing.

    A value with a YAML suffix, a path separator or naming an existing file is a path.
    """
    what = _SINGULAR.get(kind, kind)
    s = str(name_or_path)
    p = Path(s)
    if p.suffix in (".yaml", ".yml") or os.sep in s or "/" in s or p.is_file():
        if not p.is_file():
            raise ConfigError(f"{p}: no such {what} file")
        return p
    candidate = configs_dir() / kind / f"{s}.yaml"
    if not candidate.is_file():
        known = ", ".join(config_names(kind)) or "none"
        raise ConfigError(f"{what} {s!r}: no file {candidate} (known {what}s: {known})")
    return candidate
