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
