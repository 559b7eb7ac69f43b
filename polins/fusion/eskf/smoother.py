"""Rauch-Tung-Striebel smoother of the ESKF, in error-state (correction) form, over the filter's nodes.

The fast path (:mod:`polins.fusion.eskf.propagate`) keeps the filter at the ends of its
covariance steps (nodes): prior and posterior covariances, the step transitions and the
update corrections. With the filtered estimate ``x_i`` at node ``i``, the smoothed one is
``x_i (+) delta_i``::

    C_i     = P_i^+ Phi_{i+1}^T (P_{i+1}^-)^-1
    delta_i = C_i (dx_{i+1} + delta_{i+1}),            delta_last = 0
    P_i^s   = P_i^+ + C_i (P_{i+1}^s - P_{i+1}^-) C_i^T

(resets have the Jacobian I, so the corrections carry across them). A node that is not
linked to its predecessor (the yaw alignment) starts a new chain. Output rows between
nodes interpolate the smoothed corrections and covariances
(:func:`~polins.fusion.eskf.propagate.interpolate`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def rts_smooth(
    P_pre: FloatArray,
    P_post: FloatArray,
    Phi: FloatArray,
    dx: FloatArray,
    linked: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray]:
    """Smoothed corrections and covariances at the nodes (module docstring).

    Parameters
    ----------
    P_pre, P_post : (G, n, n) ndarray
        Covariances before and after the updates at each node.
    Phi : (G, n, n) ndarray
        Transition from the previous node into each node.
    dx : (G, n) ndarray
        Update corrections at each node.
    linked : (G,) bool ndarray
        False where a node starts a new chain (then ``Phi`` into it is not used).

    Returns
    -------
    delta : (G, n) ndarray
        Smoothed corrections.
    P_s : (G, n, n) ndarray
        Smoothed covariances.
    """
    G, n = dx.shape
    delta = np.zeros((G, n))
    P_s = np.array(P_post, dtype=float)
    for i in range(G - 2, -1, -1):
        if not linked[i + 1]:
            continue
        # a state with no variance yet (the default heading bias before the images set
        # it) takes no gain: solve over the others
        live = np.diag(P_pre[i + 1]) > 0.0
        C = np.zeros((n, n))
        cross = Phi[i + 1] @ P_post[i]
        C[:, live] = np.linalg.solve(P_pre[i + 1][np.ix_(live, live)], cross[live]).T
        delta[i] = C @ (dx[i + 1] + delta[i + 1])
        P_s[i] = P_post[i] + C @ (P_s[i + 1] - P_pre[i + 1]) @ C.T
    return delta, P_s
