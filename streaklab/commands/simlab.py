"""``streaklab sim-lab``: serve the simulated camera and mirror until Ctrl-C.

How other programs connect to each device: :data:`CONNECTING` (also shown by ``--help``).

Prints one ``name value`` line per address, then ``ready``, and flushes, so a
script can read the addresses from the first lines of output::

    camera 127.0.0.1:40123
    camera-data-port 40124
    streak-unit synchroscan
    scaling-table yes
    mirror /dev/pts/7
    mirror-stable /tmp/streaklab-mirror-xyz/ttySMC100
    ready

The laser-sync unit is a pyusb backend object and cannot be served to another
process; with no sync device to switch it, the laser output is on (``--dark``
turns it off).

Another program talks to the camera as to HPD-TA's RemoteEx: TCP to ``camera``
(commands) and to ``camera-data-port`` (image data), opened in either order,
each greeting read whenever it likes, then ``AppStart()``.  An Odemis-style
client (which sets ``Time Range`` to ``1 ns``) needs ``--single-sweep``.
``streaklab live`` with ``devices.camera`` set to the ``camera`` address shows
the live image.
"""
from __future__ import annotations

import signal
import sys
import threading

from streaklab.cli import CommandError


CONNECTING = """\
connecting other programs (addresses are the lines printed before 'ready'):
  camera   RemoteEx over TCP at the 'camera' host:port, images on 'camera-data-port';
           any RemoteEx client (an Odemis-style driver, streaklab's own) connects there.
  mirror   an SMC100 controller, address 1, on a serial port: open the 'mirror-stable'
           path (it follows a simulated re-plug) at 57600 baud, 8N1, Xon/Xoff, CR LF.
             pyserial      serial.Serial(PATH, 57600, xonxoff=True, timeout=1)
             pyvisa-py     pyvisa.ResourceManager("@py").open_resource("ASRL" + PATH + "::INSTR",
                               baud_rate=57600, read_termination="\\r\\n", write_termination="\\r\\n",
                               flow_control=pyvisa.constants.VI_ASRL_FLOW_XON_XOFF)
             yaqd-newport  serial_port = PATH in the newport-smc100 daemon's TOML
           then e.g. "1ID?", "1OR", "1TS" (until 32), "1PA2.5", "1TS" (until 33), "1TP".
  sync     not served to other processes (a pyusb backend object): a program in the same
           Python process takes drivers.sim.SimulatedLab().usb_backend and uses
           usb.core.find(backend=...) (python-usbtmc: usbtmc.Instrument(device)), or points
           pyusb's default backend lookup at it for pyvisa-py ("USB0::...::INSTR").
"""


def add_arguments(parser) -> None:
    import argparse

    from drivers.sim.timebase import FIDUCIAL_FRACTION, FIDUCIAL_PIXELS, FIDUCIAL_SIGMA_PS

    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = CONNECTING
    parser.add_argument("--seed", type=int, default=0, help="noise and scene seed (default 0)")
    parser.add_argument("--camera-port", type=int, default=0,
                        help="RemoteEx command port (data port = +1); default: a free ephemeral pair")
    parser.add_argument("--lines", type=int, default=16, help="scan lines of the virtual scene (default 16)")
    parser.add_argument("--x", dest="n_x", type=int, default=64, help="pixels along the slit (default 64)")
    parser.add_argument("--t", dest="n_t", type=int, default=256, help="streak rows (default 256)")
    parser.add_argument("--dark", action="store_true", help="laser output off: the camera sees dark frames only")
    parser.add_argument("--no-mirror", action="store_true", help="serve the camera only")
    parser.add_argument("--single-sweep", action="store_true",
                        help="a single-sweep streak unit (Time Range such as '1 ns') instead of synchroscan (1..4)")
    parser.add_argument("--no-scaling-table", action="store_true",
                        help="images carry no table scaling (ImgDataGet(...,ScalingTable,...) is refused)")
    tb = parser.add_argument_group(
        "time base (all off by default; see drivers/sim/timebase.py)",
        "Row r (u = r/(n_t-1), window span W ps) sees scene time t_nom(r) + n*W*4u(1-u) + delay - s_k, "
        "where t_nom is the scaling table the camera reports and s_k = jitter + drift the shift of "
        "frame k (seeded by --seed); the signal is multiplied by 1 + shading*(2u-1).")
    tb.add_argument("--jitter-ps", type=float, default=0.0, help="trigger jitter, ps RMS per frame (Gaussian)")
    tb.add_argument("--drift-ps-per-min", type=float, default=0.0,
                    help="trigger drift, ps per simulated minute (the simulator's clock, see --clock-speed)")
    tb.add_argument("--sweep-nonlinearity", type=float, default=0.0,
                    help="quadratic bow of the true row times: n*W at the middle row, 0 at the ends (|n| < 0.25)")
    tb.add_argument("--shading", type=float, default=0.0,
                    help="sensitivity ramp 1 + shading*(2u-1) along the time axis (0 <= shading < 1)")
    tb.add_argument("--clock-speed", type=float, default=1.0,
                    help="simulated seconds per wall-clock second (default 1; 60: a minute of drift per second)")
    tb.add_argument("--fiducial", action="store_true",
                    help=f"a fiducial pulse in every frame on slit pixels 0..{FIDUCIAL_PIXELS - 1} at "
                         f"{FIDUCIAL_FRACTION:g} of the window (sigma {FIDUCIAL_SIGMA_PS:g} ps), shifted like the scene")


def run(args) -> int:
    from drivers.sim.lab import SimulatedLab
    from drivers.sim.scene import VirtualScene
    from drivers.sim.timebase import TimeBase

    if not 0 <= args.camera_port <= 65534:
        raise CommandError(f"--camera-port must be 0 (any) or 1..65534, got {args.camera_port}")
    try:
        scene = VirtualScene.default(n_lines=args.lines, n_x=args.n_x, n_t=args.n_t, seed=args.seed)
    except ValueError as exc:
        raise CommandError(f"scene: {exc}") from None
    try:
        timebase = TimeBase(jitter_ps=args.jitter_ps, drift_ps_per_min=args.drift_ps_per_min,
                            sweep_nonlinearity=args.sweep_nonlinearity, shading=args.shading,
                            clock_speed=args.clock_speed, fiducial=args.fiducial)
    except ValueError as exc:
        raise CommandError(f"--{str(exc).split(' ', 1)[0].replace('_', '-')}: {exc}") from None
    lab = SimulatedLab(seed=args.seed, scene=scene, camera_port=args.camera_port,
                       mirror=not args.no_mirror, sync=False,
                       camera_options={"single_sweep": args.single_sweep, "scaling_table": not args.no_scaling_table},
                       timebase=timebase)
    try:
        lab.start()
    except (OSError, RuntimeError) as exc:
        raise CommandError(f"cannot start the simulators: {exc}") from None
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        lab.state.sync_output_enabled = not args.dark
        info = lab.describe()
        print(f"camera {info['camera']}")
        print(f"camera-data-port {info['camera_data_port']}")
        print(f"streak-unit {info['streak_unit']}")
        print(f"scaling-table {'yes' if info['scaling_table'] else 'no'}")
        if "mirror" in info:
            print(f"mirror {info['mirror']}")
            print(f"mirror-stable {info['mirror_stable']}")
        print(f"laser-output {'off' if args.dark else 'on'}")
        if timebase.fiducial:
            where = lab.fiducial_nominal()
            print(f"fiducial pixels {where['x_start']}..{where['x_stop'] - 1} row {where['row']:.3f} "
                  f"t {where['nominal_ps']:.3f} ps")
        print("ready", flush=True)
        print("streaklab sim-lab: serving; Ctrl-C to stop", file=sys.stderr, flush=True)
        while not stop.wait(0.2):
            pass
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        lab.close()
    print("streaklab sim-lab: stopped", file=sys.stderr, flush=True)
    return 0
