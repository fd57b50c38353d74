"""The import rules of docs/architecture.md, checked on the source: a lower package never imports
a higher one, nothing but the CLI, scripts and tests imports ``backpack_slam``, and the SLAM front
end and back end do not import each other."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
OURS = ("common", "segmentation", "slam", "calibration", "simulation", "backpack_slam")

# package -> the packages of ours it may import (besides itself)
ALLOWED: dict[str, set[str]] = {
    "common": set(),
    "segmentation": set(),
    "slam": {"common", "segmentation"},
    "calibration": {"common", "segmentation", "slam"},
    "simulation": {"common", "segmentation"},
    "backpack_slam": set(OURS),
}
# sub-packages that must not import each other (either direction)
SEPARATE = [("slam.frontend", "slam.backend")]


def imported_modules(root: Path, path: Path) -> list[tuple[int, str]]:
    """(line, dotted module) of every import in ``path``, absolute and relative, at any depth."""
    tree = ast.parse(path.read_text(), filename=str(path))
    parts = list(path.relative_to(root).with_suffix("").parts)
    package = parts[:-1]
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, a.name) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join([*base, node.module] if node.module else base)
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
            out.extend((node.lineno, f"{mod}.{a.name}") for a in node.names)
    return out


def module_of(root: Path, path: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def violations(root: Path = ROOT) -> list[str]:
    found: list[str] = []
    for top, allowed in ALLOWED.items():
        for path in sorted((root / top).rglob("*.py")):
            me = module_of(root, path)
            for line, mod in imported_modules(root, path):
                other = mod.split(".")[0]
                if other in OURS and other != top and other not in allowed:
                    found.append(f"{path.relative_to(root)}:{line}: {top} imports {mod}")
                for a, b in SEPARATE:
                    for x, y in ((a, b), (b, a)):
                        if within(me, x) and within(mod, y):
                            found.append(f"{path.relative_to(root)}:{line}: {x} imports {mod}")
    return sorted(set(found))


def test_import_rules_hold() -> None:
    assert violations() == []


@pytest.mark.parametrize(
    ("top", "statement"),
    [("common", "from slam.export import write_json"), ("slam", "import backpack_slam.cli"),
     ("segmentation", "from common.config import load"), ("simulation", "from slam import run")],
)
def test_a_forbidden_import_is_caught(tmp_path: Path, top: str, statement: str) -> None:
    """The check is real: a planted import of a higher package is reported."""
    (tmp_path / top).mkdir()
    (tmp_path / top / "planted.py").write_text(statement + "\n")
    assert any("planted.py" in v for v in violations(tmp_path))


def test_front_and_back_end_separation_is_caught(tmp_path: Path) -> None:
    (tmp_path / "slam" / "frontend").mkdir(parents=True)
    (tmp_path / "slam" / "frontend" / "x.py").write_text("from slam.backend import Backend\n")
    assert violations(tmp_path) == ["slam/frontend/x.py:1: slam.frontend imports slam.backend",
                                    "slam/frontend/x.py:1: slam.frontend imports slam.backend.Backend"]


MAX_CLASS_LINES = 400


def test_no_class_in_slam_is_over_400_lines() -> None:
    """The runner and the back end stay split by job (issue 20): no class of slam/ over 400 lines."""
    big = []
    for path in sorted((ROOT / "slam").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and (n := (node.end_lineno or node.lineno) - node.lineno + 1) > MAX_CLASS_LINES:
                big.append(f"{path.relative_to(ROOT)}:{node.name} ({n} lines)")
    assert big == []
