"""common/atomic.py: a folder written under a temporary name leaves nothing behind when the
block fails or an interrupt lands, even right after the temporary folder is made."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.atomic import atomic_dir


def _left(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_a_completed_block_replaces_the_folder(tmp_path: Path) -> None:
    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with atomic_dir(out) as tmp:
        (tmp / "new.txt").write_text("new")
    assert _left(tmp_path) == ["run"] and _left(out) == ["new.txt"]


def test_a_failing_block_leaves_the_folder_as_it_was(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        with atomic_dir(out) as tmp:
            (tmp / "half.txt").write_text("half")
            raise KeyboardInterrupt
    assert _left(tmp_path) == []


def test_an_interrupt_right_after_the_temporary_folder_is_made_removes_it(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A signal handled at the first instruction after ``mkdir`` (the fuzz campaign's SIGTERM,
    sent as soon as the temporary folder appears, once left it behind)."""
    real = Path.mkdir

    def mkdir_then_interrupt(self: Path, *args: object, **kwargs: object) -> None:
        real(self, *args, **kwargs)  # type: ignore[arg-type]
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "mkdir", mkdir_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        with atomic_dir(tmp_path / "run"):
            pass
    monkeypatch.undo()
    assert _left(tmp_path) == []



def test_a_folder_a_helper_still_writes_into_is_removed_all_the_same(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """discard tries again while files still appear: here a helper's last file lands in the
    folder just as the first removal ends."""
    import shutil

    import common.atomic as atomic

    real = shutil.rmtree
    calls: list[int] = []

    def rmtree_then_late_write(path: Path, ignore_errors: bool = False) -> None:
        real(path, ignore_errors=ignore_errors)
        calls.append(1)
        if len(calls) == 1:  # the helper's late file: the folder is back with it
            path.mkdir()
            (path / "part_7.bin").write_bytes(b"x")

    monkeypatch.setattr(atomic.shutil, "rmtree", rmtree_then_late_write)
    once = tmp_path / ".once.tmp-x"
    once.mkdir()
    atomic.discard(once, attempts=1)
    assert once.exists()  # one removal is not enough
    calls.clear()
    tmp = tmp_path / ".run.tmp-x"
    tmp.mkdir()
    atomic.discard(tmp)
    assert not tmp.exists() and len(calls) == 2
