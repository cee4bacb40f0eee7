"""Device drivers: interfaces, real wire-protocol drivers, and simulators (drivers.sim)."""
from .errors import ConnectionLost, DeviceError, DeviceTimeout, DriverError, ProtocolError  # noqa: F401
from .interfaces import LaserSync, ScanMirror, StreakCamera, StreakImage  # noqa: F401
