"""Numerical helpers shared by the tests."""

import numpy as np


def numjac(fun, n=15, eps=1e-7):
    """Central-difference Jacobian of ``fun`` at 0 (``n`` inputs, step ``eps``)."""
    cols = []
    for i in range(n):
        d = np.zeros(n)
        d[i] = eps
        cols.append((fun(d) - fun(-d)) / (2 * eps))
    return np.stack(cols, axis=-1)
