"""The state of the virtual lab, shared by the three simulators.

The mirror simulator writes the angle, the sync simulator the delay and output
state, and the camera simulator reads all of them when it renders a frame.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass, field


@dataclass
class LabState:
    """Mutable physical state of the virtual rig.  Guard multi-field reads with ``lock``."""

    mirror_angle_deg: float = 0.0
    mirror_referenced: bool = False
    sync_output_enabled: bool = False
    sync_delay_ps: float = 0.0
    sync_rate_hz: float = 80e6
    lock: threading.RLock = field(default_factory=threading.RLock, repr=False, compare=False)
