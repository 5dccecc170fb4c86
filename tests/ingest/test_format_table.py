"""The readers are one table keyed by suffix (pointflow/formats): every suffix has a reader,
a path's reader is found by its suffix or a named format, and an unknown suffix is one
clear error naming the file and the suffixes known."""
from __future__ import annotations

import numpy as np
import pytest

from pointflow import formats
from pointflow.formats import FORMATS, READERS, FormatError, reader_for


def test_the_table_holds_every_format():
    assert set(FORMATS) == set(READERS) >= {"las", "laz", "ply", "pcd", "npy", "npz", "csv", "xyz", "txt", "bin"}
    for suffix, reader in READERS.items():
        assert reader.name == suffix and callable(reader.read)


def test_a_reader_by_suffix_or_by_name(tmp_path):
    assert reader_for(str(tmp_path / "a.PLY")) is READERS["ply"]
    assert reader_for(str(tmp_path / "scan.copc.laz")) is READERS["laz"]
    assert reader_for(str(tmp_path / "a.dat"), "csv") is READERS["csv"]


def test_an_unknown_suffix_names_the_file_and_the_suffixes(tmp_path):
    path = str(tmp_path / "cloud.e57")
    with pytest.raises(FormatError) as info:
        reader_for(path)
    assert info.value.key == path
    assert "'e57'" in info.value.message and all(s in info.value.message for s in FORMATS)
    with pytest.raises(FormatError, match="unsupported format 'e57'"):
        formats.read(str(tmp_path / "a.ply"), "e57")


def test_read_goes_through_the_table(tmp_path):
    pos = np.arange(12, dtype=np.float32).reshape(4, 3)
    path = str(tmp_path / "a.ply")
    formats.write_ply(path, pos, {"intensity": np.arange(4, dtype=np.float32)})
    got, ch = formats.read(path)
    np.testing.assert_allclose(got, pos)
    np.testing.assert_allclose(ch["intensity"], np.arange(4))
