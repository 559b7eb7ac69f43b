"""The process pool of the image stage, fed by its own thread (polins.loop.measurer.FedPool)."""

from __future__ import annotations

import math
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor

import pytest

from polins.loop.measurer import FedPool


def test_fed_pool_returns_results_and_errors_in_order_of_submission():
    pool = FedPool(ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")))
    futures = [pool.submit(math.sqrt, float(k)) for k in range(5)]
    bad = pool.submit(math.sqrt, -1.0)
    assert [f.result(timeout=60) for f in futures] == [math.sqrt(k) for k in range(5)]
    with pytest.raises(ValueError, match="math domain error"):
        bad.result(timeout=60)
    pool.shutdown(wait=True)
    with pytest.raises(RuntimeError, match="after shutdown"):  # as the pool itself
        pool.submit(math.sqrt, 4.0)
