"""The navigation loop: images measured with the INS attitude as prior, streaming and offline.

:mod:`polins.loop.options` (what the loop does), :mod:`polins.loop.measurer` (the image
stage and its executors), :mod:`polins.loop.prior` (the prior and the sun vector of an
image), :mod:`polins.loop.stream` (:class:`NavigationStream`, the streaming state machine),
:mod:`polins.loop.tables` (measurement rows and events), :mod:`polins.loop.offline`
(:func:`run_log` over a recorded log).
"""

from polins.loop.offline import run_log
from polins.loop.options import LoopOptions
from polins.loop.stream import NavigationStream, StreamState

__all__ = ["LoopOptions", "NavigationStream", "StreamState", "run_log"]
