"""Data set folders: chunked resumable writing, completeness marker, memory-mapped reading."""

import numpy as np
import pytest

from neumip.groundtruth.dataset import DatasetError, DatasetWriter, open_dataset, write_dataset
from neumip.core.contract import random_queries


def test_interrupted_write_is_never_complete_and_resumes(tmp_path):
    q, rgb = random_queries(10, seed=1), np.random.default_rng(0).random((10, 3), np.float32)
    writer = DatasetWriter(tmp_path / "d", 10, 4, {"seed": 1})
    writer.write_chunk(0, q[:4], rgb[:4])
    del writer  # "interrupted"
    with pytest.raises(DatasetError, match="incomplete"):
        open_dataset(tmp_path / "d")
    with pytest.raises(DatasetError, match=r"other settings \(seed: there 1, asked 2\)"):
        DatasetWriter(tmp_path / "d", 10, 4, {"seed": 2})
    resumed = DatasetWriter(tmp_path / "d", 10, 4, {"seed": 1})
    assert resumed.done == 1
    with pytest.raises(DatasetError, match="out of order"):
        resumed.write_chunk(2, q[8:], rgb[8:])
    resumed.write_chunk(1, q[4:8], rgb[4:8])
    with pytest.raises(DatasetError, match="cannot finalize"):
        resumed.finalize()
    resumed.write_chunk(2, q[8:], rgb[8:])
    ds = resumed.finalize()
    np.testing.assert_array_equal(ds.queries, q)
    np.testing.assert_array_equal(ds.rgb, rgb)
    assert isinstance(ds.queries, np.memmap) and not (tmp_path / "d" / "progress.json").exists()


def test_write_dataset_validates_rows(tmp_path):
    q = random_queries(5)
    q[2, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        write_dataset(tmp_path / "x", q, np.zeros((5, 3)), {})
    with pytest.raises(ValueError, match="shape"):
        write_dataset(tmp_path / "y", random_queries(5), np.zeros((4, 3)), {})


def test_a_damaged_data_set_is_an_error_naming_its_file(tmp_path):
    """A truncated array is refused, never grown with zeros when a partial data set resumes (numpy's r+ memmap
    would), nor mapped when a complete one opens; a damaged meta.json or progress.json names itself."""
    q, rgb = random_queries(1000, seed=2), np.random.default_rng(1).random((1000, 3), np.float32)
    writer = DatasetWriter(tmp_path / "partial", 1000, 400, {"seed": 1})
    writer.write_chunk(0, q[:400], rgb[:400])
    del writer  # "interrupted"
    queries = tmp_path / "partial" / "queries.npy"
    size = queries.stat().st_size
    with queries.open("r+b") as f:
        f.truncate(size // 2)
    with pytest.raises(DatasetError, match=r"queries\.npy is damaged: it holds .* bytes of the"):
        DatasetWriter(tmp_path / "partial", 1000, 400, {"seed": 1})
    assert queries.stat().st_size == size // 2  # not grown back

    write_dataset(tmp_path / "whole", q, rgb, {"seed": 1})
    (tmp_path / "whole" / "rgb.npy").write_bytes((tmp_path / "whole" / "rgb.npy").read_bytes()[:90])
    with pytest.raises(DatasetError, match=r"rgb\.npy is damaged"):
        open_dataset(tmp_path / "whole")
    (tmp_path / "whole" / "meta.json").write_text('{"format": "neumip-mbtf-1", "n": ')
    with pytest.raises(DatasetError, match=r"meta\.json is damaged"):
        open_dataset(tmp_path / "whole")
    with pytest.raises(DatasetError, match=r"meta\.json is damaged"):
        DatasetWriter(tmp_path / "whole", 1000, 400, {"seed": 1})
    write_dataset(tmp_path / "version", q, rgb, {"seed": 1})
    data = bytearray((tmp_path / "version" / "queries.npy").read_bytes())
    data[6] = 9  # the format's major version
    (tmp_path / "version" / "queries.npy").write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=r"queries\.npy is damaged .*version"):
        open_dataset(tmp_path / "version")
    (tmp_path / "partial" / "progress.json").write_text("[1, 2]")
    with pytest.raises(DatasetError, match=r"progress\.json is damaged"):
        DatasetWriter(tmp_path / "partial", 1000, 400, {"seed": 1})
