"""Fusion of the IMU with the polarization compass: one configuration, two backends, one solution table.

Data flow::

    imu table ─────────► inputs.validate_imu ──────────────┐
    measurements table ► inputs.validate_measurements      │
                         └► items.items_from_table ───┐    │
                                                      ▼    ▼
    config.FuseConfig ──► api.run_fusion ─► eskf (blocks ► dynamics ► filter ► propagate
                          (api.fuse)        [► smoother])  or  graph.fuse_graph (GTSAM)
                                │
                                ▼
               state.NavState ─► state.solution_table ─► result.FusionResult
                                                (solution, updates, filtered, events)

Both backends linearize their measurement items with :func:`items.item_model` (the shared
``(z, H, R)`` models of :mod:`polins.fusion.measurement`) and gate them with
:func:`items.gate_limit`. Streaming use: :func:`build_filter` returns the
:class:`~polins.fusion.eskf.ESKF` (``polins.loop`` drives it). Data faults (impossible IMU
samples, IMU gaps, unusable sigmas) are skipped and reported as events, and the yaw is
acquired by consensus (:mod:`polins.fusion.eskf.acquisition`; docs/filter.md, sections 7.1
and 7.2).
"""

from polins.fusion.api import build_filter, fuse, run_fusion
from polins.fusion.config import FuseConfig
from polins.fusion.eskf import ESKF
from polins.fusion.inputs import output_mask
from polins.fusion.items import records_table
from polins.fusion.result import FUSION_EVENT_KINDS, FusionEvent, FusionResult
from polins.ins.state import NavState, solution_table
from polins.site import Site

__all__ = [
    "ESKF",
    "FUSION_EVENT_KINDS",
    "FuseConfig",
    "FusionEvent",
    "FusionResult",
    "NavState",
    "Site",
    "build_filter",
    "fuse",
    "output_mask",
    "records_table",
    "run_fusion",
    "solution_table",
]
