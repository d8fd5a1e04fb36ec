"""Test plants built with python-control.

* :func:`wafer_stage`: the SISO OAT-like wafer stage of the paper's
  experimental section in closed loop (:mod:`lrmfrf.plants.siso_stage`).
* :func:`mimo_wafer_stage`: the MIMO OAT-like stage, four corner actuators,
  four encoders and a point-of-interest sensor, under decoupled feedback
  (:mod:`lrmfrf.plants.mimo_stage`).
* :func:`random_stage`: random stages of both kinds with checked loops, to test
  on stages nobody tuned on (:mod:`lrmfrf.plants.random_stages`).
* :mod:`lrmfrf.plants.loops`: the lead-PID controller, closed loops
  ``P (I + C P_y)^-1`` and stability margins shared by the plants.
"""

from .loops import Margins, lead_pid_controller, loop_margins
from .mimo_stage import (
    DEFAULT_PLATE_MODES,
    MIMOWaferStage,
    PlateMode,
    mimo_wafer_stage,
    plate_plant,
)
from .random_stages import RandomDraw, random_stage
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
    "DEFAULT_PLATE_MODES",
    "MIMOWaferStage",
    "Margins",
    "Mode",
    "PlateMode",
    "RandomDraw",
    "WaferStage",
    "closed_loop",
    "lead_pid_controller",
    "loop_margins",
    "mimo_wafer_stage",
    "modal_plant",
    "plate_plant",
    "random_stage",
    "wafer_stage",
]
