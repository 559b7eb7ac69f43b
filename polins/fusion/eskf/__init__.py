"""The error-state Kalman filter (ESKF): error-state blocks, dynamics, the filter, its fast path and smoother.

Modules: :mod:`~polins.fusion.eskf.blocks` (the named blocks of the error state),
:mod:`~polins.fusion.eskf.dynamics` (continuous error dynamics, Van Loan discretisation),
:mod:`~polins.fusion.eskf.filter` (:class:`ESKF`: streaming filter, measurement queue,
gate, resets, self-alignment), :mod:`~polins.fusion.eskf.alignment` (levelling, the yaw
offset of a heading), :mod:`~polins.fusion.eskf.acquisition` (the yaw acquired by
consensus and re-acquired, the covariance over an IMU gap),
:mod:`~polins.fusion.eskf.propagate` (the fast offline path),
:mod:`~polins.fusion.eskf.smoother` (Rauch-Tung-Striebel).
"""

from polins.fusion.eskf.blocks import Block, Layout, error_blocks
from polins.fusion.eskf.dynamics import StepNominal, discretize, nav_error_dynamics
from polins.fusion.eskf.filter import ESKF
from polins.fusion.eskf.smoother import rts_smooth

__all__ = [
    "ESKF",
    "Block",
    "Layout",
    "StepNominal",
    "discretize",
    "error_blocks",
    "nav_error_dynamics",
    "rts_smooth",
]
