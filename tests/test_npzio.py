"""npzio.read_npz on archives built member by member here (zipfile and numpy's .npy writer): what it must
read, and what it must refuse before numpy decodes it."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

from mi_bivariate.errors import InputError
from mi_bivariate.npzio import read_npz


def _npy(array: np.ndarray, version=None) -> bytes:
    """``array`` as ``.npy`` bytes (numpy's writer, at ``version`` if given)."""
    out = io.BytesIO()
    np.lib.format.write_array(out, array, version=version)
    return out.getvalue()


def _archive(path: Path, members: dict) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        for name, payload in members.items():
            zf.writestr(name, payload)
    return path


def test_every_npy_version_numpy_writes_is_read(tmp_path):
    """.npy 1.0, 2.0 (numpy's for a header over 64 KiB) and 3.0 (for a UTF-8 header) members are all read,
    exactly."""
    table = np.arange(12, dtype=np.float32).reshape(3, 4) / 7
    for version in ((1, 0), (2, 0), (3, 0)):
        path = _archive(tmp_path / f"v{version[0]}.npz", {"table.npy": _npy(table, version)})
        got = read_npz(path, required=("table",))
        assert list(got) == ["table"] and got["table"].dtype == np.float32
        np.testing.assert_array_equal(got["table"], table)


def test_a_member_holding_more_than_its_header_declares_is_refused(tmp_path):
    """A .npy header declaring 2 values over a member of 4 (numpy would read the first 2 and drop the rest
    without a word) is refused, as one declaring more than it holds is."""
    payload = _npy(np.arange(4, dtype=np.float64)).replace(b"(4,)", b"(2,)")
    path = _archive(tmp_path / "short.npz", {"table.npy": payload})
    with pytest.raises(InputError, match=r"short.npz: member 'table.npy' is 32 bytes where its header declares 16"):
        read_npz(path)


@pytest.mark.parametrize("text", [np.array([b"0.1", b"0.2"]), np.array(["0.1", "0.2"])])
def test_text_is_refused_where_numbers_go_in_bytes_or_unicode(tmp_path, text):
    """Numbers stored as text, byte strings (``S``) as much as unicode (``U``), are refused outside the text
    members (``numpy.asarray(...).astype(float)`` would read ``b"0.1"`` as 0.1 without a word); a text
    member may hold either."""
    path = _archive(tmp_path / "text.npz", {"table.npy": _npy(text), "meta.npy": _npy(np.array(b"{}"))})
    with pytest.raises(InputError, match=rf"text.npz: member 'table' holds text \({text.dtype}\), not numbers"):
        read_npz(path)
    assert read_npz(path, text=("meta", "table"))["table"].tolist() == text.tolist()


def test_a_folder_or_an_archive_too_large_for_memory_is_one_input_error(tmp_path, monkeypatch):
    """A folder given as the archive is 'not a file' (not an operating-system error about permissions); an
    archive within the limits that still does not fit in memory is 'too large to read', not a MemoryError."""
    (tmp_path / "brdf.npz").mkdir()
    with pytest.raises(InputError, match=r"brdf.npz: not a file \(give the path of a .npz file, not of a folder\)"):
        read_npz(tmp_path / "brdf.npz")
    path = _archive(tmp_path / "big.npz", {"table.npy": _npy(np.zeros(4))})

    def no_memory(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(np, "load", no_memory)
    with pytest.raises(InputError, match="big.npz: too large to read: not a table file"):
        read_npz(path, what="table file")
