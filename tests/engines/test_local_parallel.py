"""LocalMaterials' concurrent chunks: same answers as one call, chunk sizes, session options."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import onnxruntime as ort
import pytest

from neumip.core import contract as C
from neumip.engines.local import DEFAULT_CHUNK, MIN_SPLIT, LocalMaterials, load_material, run_chunked, split_chunk
from neumip.core.contract import random_queries


@pytest.mark.parametrize("rows", [0, 1, MIN_SPLIT * 2 + 3, 50_001])
def test_concurrent_chunks_match_one_call(model_dir, rows):
    q = random_queries(rows, seed=rows)
    direct = ort.InferenceSession(str(model_dir / "rand16.onnx")).run(None, {C.ONNX_INPUT: q})[0]
    mats = LocalMaterials(model_dir, threads=3, chunk=4096)
    np.testing.assert_array_equal(mats.evaluate("rand16", q), direct)


def test_run_chunked_with_executor_fills_every_row(model_dir):
    session = load_material(model_dir / "rand16.onnx", threads=1).run
    q = random_queries(10_007, seed=2)
    with ThreadPoolExecutor(4) as pool:
        parallel = run_chunked(session, q, 1000, pool)
    np.testing.assert_array_equal(parallel, run_chunked(session, q, 1000))


def test_split_chunk_shares_rows_between_workers():
    assert split_chunk(100_000, 2, chunk=4096) == 3847  # 26 calls <= chunk: a multiple of the workers
    assert split_chunk(4 * DEFAULT_CHUNK, 2) == DEFAULT_CHUNK
    assert split_chunk(10_000, 2, chunk=8192) == 5000
    assert split_chunk(1000, 2, chunk=8192) == MIN_SPLIT  # too small to split
    assert split_chunk(10_000, 1, chunk=8192) == 8192
    assert split_chunk(10_000, 2, chunk=100) == 100  # an explicit small chunk is kept


def test_sessions_do_not_spin(model_dir):
    """The option is read back from the session: pool threads sleep between ops."""
    material = load_material(model_dir / "rand16.onnx", threads=2)
    entries = material.session.get_session_options().get_session_config_entry(
        "session.intra_op.allow_spinning")
    assert entries == "0"
