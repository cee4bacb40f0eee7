"""Simulated devices that speak the real wire protocols over the real transports.

``drivers.sim.SimulatedLab`` (camera, mirror and laser sync on one shared state)
is imported on first use, so importing one simulator never pulls in the others.
"""


def __getattr__(name):
    if name == "SimulatedLab":
        from .lab import SimulatedLab

        return SimulatedLab
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
