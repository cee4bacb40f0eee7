"""The state of the virtual lab, shared by the three simulators.

The mirror simulator writes the angle, the sync simulator the delay and output
state, and the camera simulator reads all of them when it renders a frame.  The camera
adds one trigger to ``triggers`` for every frame it takes while the sync output is on; the
sync simulator measures and removes them (``:TINTerval:FETCh?``).
"""
from __future__ import annotations

import collections
import threading
from dataclasses import dataclass, field

#: trigger intervals the sync unit's measurement buffer holds; the oldest are lost beyond it
TRIGGER_BUFFER = 65536


@dataclass
class LabState:
    """Mutable physical state of the virtual rig.  Guard multi-field reads with ``lock``."""

    mirror_angle_deg: float = 0.0
    mirror_referenced: bool = False
    sync_output_enabled: bool = False
    sync_delay_ps: float = 0.0
    sync_rate_hz: float = 80e6
    #: ``(interval_ps, noise_key)`` of each camera trigger not yet read out: the trigger's true time
    #: after its laser pulse (ps) and the entropy that seeds its measurement noise
    triggers: collections.deque = field(default_factory=lambda: collections.deque(maxlen=TRIGGER_BUFFER),
                                        repr=False, compare=False)
    lock: threading.RLock = field(default_factory=threading.RLock, repr=False, compare=False)
