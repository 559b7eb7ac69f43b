"""The stream's IMU sample queue (polins.loop.samples) against a plain list of samples."""

import numpy as np
import pytest

from polins.loop.samples import SampleQueue


def test_sample_queue_keeps_order_across_growth_and_compaction():
    """Blocks appended and taken in random sizes (the storage compacted and doubled on the
    way) give back exactly the samples of a reference list, in order."""
    rng = np.random.default_rng(5)
    queue = SampleQueue(capacity=4)
    reference: list[tuple[float, np.ndarray, np.ndarray]] = []
    t_next = 0.0
    taken_t: list[float] = []
    for _ in range(200):
        m = int(rng.integers(0, 9))
        t = t_next + 0.005 * np.arange(1, m + 1)
        t_next = float(t[-1]) if m else t_next
        w, f = rng.normal(size=(m, 3)), rng.normal(size=(m, 3))
        queue.extend(t, w, f)
        reference += list(zip(t.tolist(), w, f, strict=True))
        assert len(queue) == len(reference)
        np.testing.assert_array_equal(queue.t, [s[0] for s in reference])
        if reference:
            i = int(rng.integers(-len(reference), len(reference)))
            t_i, w_i, f_i = queue.sample(i)
            assert t_i == reference[i][0]
            np.testing.assert_array_equal(w_i, reference[i][1])
            np.testing.assert_array_equal(f_i, reference[i][2])
        n = int(rng.integers(0, 8))
        if rng.random() < 0.5:
            t_out, w_out, f_out = queue.take(n)
            np.testing.assert_array_equal(w_out, np.reshape([s[1] for s in reference[:n]], (-1, 3)))
            np.testing.assert_array_equal(f_out, np.reshape([s[2] for s in reference[:n]], (-1, 3)))
            taken_t += t_out.tolist()
        else:
            queue.drop(n)
        reference = reference[n:]
    np.testing.assert_array_equal(queue.gyro_b, np.reshape([s[1] for s in reference], (-1, 3)))
    np.testing.assert_array_equal(queue.accel_b, np.reshape([s[2] for s in reference], (-1, 3)))
    assert np.all(np.diff(taken_t) > 0)  # what was taken came out in time order
    with pytest.raises(IndexError):
        queue.sample(len(queue))
    queue.clear()
    assert len(queue) == 0 and queue.t.shape == (0,)
