"""Fusion of the IMU with the polarization compass: one configuration, two backends, one solution table.

Data flow::

    imu table ─────────► inputs.validate_imu ──────────────┐  (faults: the fault policy)
    measurements table ► inputs.validate_measurements      │
                         └► items.items_from_table ───┐    │
                                                      ▼    ▼
    config.FuseConfig ──► inputs.prepare ─► eskf.batch.fuse_eskf (blocks ► dynamics ► filter
                          (api.run_fusion,   ► propagate [► smoother])  or
                           api.fuse)         graph.fuse_graph (GTSAM)
                                │
                                ▼
               state.NavState ─► state.solution_table ─► result.FusionResult
                                                (solution, updates, filtered, events)

Both backends linearize their measurement items with :func:`items.item_model` (the shared
``(z, H, R)`` models of :mod:`polins.fusion.measurement`) and gate them with
:func:`items.gate_limit`. Streaming use: :func:`build_filter` returns the
:class:`~polins.fusion.eskf.ESKF` (``polins.loop`` drives it). Data faults (impossible IMU
samples, IMU gaps, unusable sigmas) are skipped and reported as events
(:mod:`polins.fusion.faults`, the one policy of every path), and the yaw is
acquired by consensus (:mod:`polins.fusion.eskf.acquisition`; docs/filter.md, sections 7.1
and 7.2).
"""

from polins.fusion.api import build_filter, fuse, run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.eskf import ESKF
from polins.fusion.faults import EventKind, FusionEvent, ImplausibleRunError, ImuUnitsError
from polins.fusion.inputs import output_mask
from polins.fusion.items import records_table
from polins.fusion.result import FusionResult
from polins.ins.state import NavState, solution_table
from polins.site import Site

__all__ = [
    "ESKF",
    "EventKind",
    "FuseConfig",
    "FusionEvent",
    "FusionResult",
    "ImplausibleRunError",
    "ImuUnitsError",
    "NavState",
    "Site",
    "build_filter",
    "fuse",
    "output_mask",
    "records_table",
    "run_fusion",
    "solution_table",
]
