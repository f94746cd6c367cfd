"""atomic.py's refusals, checked on the file system itself: an output that is an input by another path (a
hard link, a symbolic link), one file named twice, a folder; a set of writes naming one file twice; and a
set of writes stopped between its renames, or failing in its second file."""

from __future__ import annotations

import os

import pytest

from mi_bivariate import atomic
from mi_bivariate.atomic import atomic_paths, check_outputs
from mi_bivariate.errors import InputError, Terminated


def test_an_output_that_is_an_input_by_another_path_is_refused(tmp_path):
    """The same file on disk is refused whatever the path says: a hard link to the input (only the inode
    tells), a symbolic link to it, and the input spelt with ``..``. Nothing is written or removed."""
    photo = tmp_path / "photo.exr"
    photo.write_bytes(b"input")
    os.link(photo, tmp_path / "hard.exr")
    os.symlink(photo, tmp_path / "soft.exr")
    (tmp_path / "sub").mkdir()
    before = sorted(p.name for p in tmp_path.iterdir())
    for out in (tmp_path / "hard.exr", tmp_path / "soft.exr", tmp_path / "sub" / ".." / "photo.exr"):
        with pytest.raises(InputError, match=rf"{out.name}: output would overwrite the input {photo}"):
            check_outputs([out], [photo])
    assert sorted(p.name for p in tmp_path.iterdir()) == before and photo.read_bytes() == b"input"


def test_one_output_named_twice_or_a_folder_is_refused_before_work(tmp_path):
    """Two outputs that are one file (``a.npz`` and ``sub/../a.npz``) are 'written twice'; an output that is
    an existing folder is refused as one. (Left to the write, the second would silently replace the first,
    and the folder would fail only after the work.)"""
    (tmp_path / "sub").mkdir()
    with pytest.raises(InputError, match=r"a.npz: is written twice by this command \(choose another --out\)"):
        check_outputs([tmp_path / "a.npz", tmp_path / "sub" / ".." / "a.npz"])
    with pytest.raises(InputError, match=r"sub: output is a directory \(give a file name\)"):
        check_outputs([tmp_path / "b.npz", tmp_path / "sub"])


def test_a_set_of_writes_naming_one_file_twice_is_refused_before_any_temporary(tmp_path):
    """atomic_paths renames its temporaries in turn, so a destination named twice would keep whichever came
    last: refused (a ValueError: a caller's mistake, not the user's) before any file is made."""
    with pytest.raises(ValueError, match="duplicate destinations"):
        with atomic_paths([tmp_path / "x.npz", tmp_path / "." / "x.npz"]):
            pass
    assert list(tmp_path.iterdir()) == []


def test_a_stop_between_the_renames_of_a_set_waits_until_all_are_in_place(tmp_path, monkeypatch):
    """A stop (the CLI's SIGTERM handler) asked right after the first of two renames is held until the second
    is done, then raised: the set is all in place, never one file new and its partner missing."""
    handler = atomic.stop_on_signal(Terminated)
    publish = atomic._publish

    def publish_then_stop(tmp, path):
        publish(tmp, path)
        handler(15, None)

    monkeypatch.setattr(atomic, "_publish", publish_then_stop)
    with pytest.raises(Terminated):
        with atomic_paths([tmp_path / "table.npz", tmp_path / "table.json"]) as (table, record):
            table.write_bytes(b"table")
            record.write_bytes(b"record")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == {"table.npz": b"table", "table.json": b"record"}
    assert atomic._held == 0 and atomic._pending is None


def test_a_failed_write_of_a_set_names_the_file_that_failed(tmp_path):
    """A full disk while the second file of a set is written is one InputError naming that file (not the
    temporary, nor the set's first file), and neither file nor any temporary is left."""
    with pytest.raises(InputError, match=r"table.json: cannot be written \(No space left on device\)"):
        with atomic_paths([tmp_path / "table.npz", tmp_path / "table.json"]) as (table, record):
            table.write_bytes(b"table")
            raise OSError(28, "No space left on device", str(record))
    assert list(tmp_path.iterdir()) == []


def test_an_output_in_folders_yet_to_be_made_is_accepted_and_written(tmp_path):
    """Outputs go into folders made for them: ``new/deeper/x.npz`` passes the check (its nearest existing
    folder is writable), and the write makes the folders."""
    out = tmp_path / "new" / "deeper" / "x.npz"
    check_outputs([out])
    assert list(tmp_path.iterdir()) == []          # the check made nothing
    with atomic_paths([out]) as (tmp,):
        tmp.write_bytes(b"x")
    assert out.read_bytes() == b"x"
