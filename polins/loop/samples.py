"""IMU samples held by the stream: a first-in first-out queue of times, rates and forces in numpy arrays.

:class:`SampleQueue` keeps ``(N,)`` times [s], ``(N, 3)`` body rates [rad/s] and specific
forces [m/s^2] in preallocated arrays, appended in blocks at the back and taken from the
front: no Python object per sample. The live samples are views (:attr:`SampleQueue.t`,
:attr:`gyro_b`, :attr:`accel_b`); the storage is compacted or doubled when the back is
reached, so appending costs O(1) per sample on average.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Sample = tuple[float, FloatArray, FloatArray]  # (t [s], gyro_b [rad/s], accel_b [m/s^2])


class SampleQueue:
    """IMU samples in time order, appended at the back, taken from the front (module docstring).

    Parameters
    ----------
    capacity : int
        Initial storage [samples]; grows as needed.
    """

    def __init__(self, capacity: int = 1024) -> None:
        self._t = np.empty(capacity)
        self._w = np.empty((capacity, 3))
        self._f = np.empty((capacity, 3))
        self._a = 0  # the live samples are [_a, _b)
        self._b = 0

    def __len__(self) -> int:
        return self._b - self._a

    @property
    def t(self) -> FloatArray:
        """Times of the samples [s], ``(N,)`` (a view)."""
        return self._t[self._a : self._b]

    @property
    def gyro_b(self) -> FloatArray:
        """Body rates [rad/s], ``(N, 3)`` (a view)."""
        return self._w[self._a : self._b]

    @property
    def accel_b(self) -> FloatArray:
        """Specific forces [m/s^2], ``(N, 3)`` (a view)."""
        return self._f[self._a : self._b]

    def sample(self, i: int) -> Sample:
        """Sample ``i`` (from the front; negative from the back) as ``(t, gyro_b, accel_b)``
        (copies)."""
        k = (self._b if i < 0 else self._a) + i
        if not self._a <= k < self._b:
            raise IndexError(f"sample {i} of a queue of {len(self)}")
        return float(self._t[k]), self._w[k].copy(), self._f[k].copy()

    def extend(self, t: FloatArray, gyro_b: FloatArray, accel_b: FloatArray) -> None:
        """Append samples ``(M,)``, ``(M, 3)``, ``(M, 3)`` at the back."""
        m = t.shape[0]
        if self._b + m > self._t.shape[0]:
            self._make_room(m)
        self._t[self._b : self._b + m] = t
        self._w[self._b : self._b + m] = gyro_b
        self._f[self._b : self._b + m] = accel_b
        self._b += m

    def take(self, n: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Remove the first ``n`` samples and return them (copies)."""
        a = self._a
        n = min(n, len(self))
        out = (self._t[a : a + n].copy(), self._w[a : a + n].copy(), self._f[a : a + n].copy())
        self.drop(n)
        return out

    def drop(self, n: int) -> None:
        """Forget the first ``n`` samples (``n >= 0``)."""
        self._a += min(max(n, 0), len(self))
        if self._a == self._b:
            self._a = self._b = 0

    def clear(self) -> None:
        """Forget every sample."""
        self._a = self._b = 0

    def _make_room(self, m: int) -> None:
        """Room for ``m`` more samples: the live ones moved to the front, the storage
        doubled when that is not enough."""
        n = len(self)
        size = self._t.shape[0]
        while n + m > size:
            size *= 2
        if size != self._t.shape[0]:
            t, w, f = np.empty(size), np.empty((size, 3)), np.empty((size, 3))
        else:
            t, w, f = self._t, self._w, self._f
        t[:n] = self._t[self._a : self._b]
        w[:n] = self._w[self._a : self._b]
        f[:n] = self._f[self._a : self._b]
        self._t, self._w, self._f = t, w, f
        self._a, self._b = 0, n


__all__ = ["Sample", "SampleQueue"]
