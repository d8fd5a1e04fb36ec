"""Test plants built with python-control.

* :func:`wafer_stage`: the SISO OAT-like wafer stage of the paper's
  experimental section in closed loop (:mod:`lrmfrf.plants.siso_stage`).
* :mod:`lrmfrf.plants.loops`: the lead-PID controller, closed loops
  ``P (I + C P_y)^-1`` and stability margins shared by the plants.
"""

from .loops import Margins, lead_pid_controller, loop_margins
from .siso_stage import (
    DEFAULT_MODES,
    Mode,
    WaferStage,
    closed_loop,
    modal_plant,
    wafer_stage,
)

__all__ = [
    "DEFAULT_MODES",
    "Margins",
    "Mode",
    "WaferStage",
    "closed_loop",
    "lead_pid_controller",
    "loop_margins",
    "modal_plant",
    "wafer_stage",
]
