"""Scan configuration: a TOML file read with the standard library, validated key by key.

A configuration has these sections (every key is listed with its default; see
``acquisition/examples/sim_scan.toml`` for a commented example)::

    [devices]
    camera = "127.0.0.1:1001"      # RemoteEx command port "host:port" (data port = port + 1)
    mirror = "/dev/ttyUSB0"        # serial port name or pyserial URL of the motion controller
    mirror_address = 1             # controller address on the serial line (1..31)
    mirror_xonxoff = true          # Xon/Xoff flow control on the mirror's serial port (SMC100 manual)
    sync_vendor_id = 0x0000        # USB vendor id of the laser-sync unit      } give both ids,
    sync_product_id = 0x0000       # USB product id                            } or the serial,
    sync_serial = ""               # USB serial number                         } or all three
    timeout_s = 5.0                # reply timeout of one device command, every driver

    [scan]                         # either start_deg/stop_deg/count or angles_deg
    start_deg = -5.0
    stop_deg = 5.0
    count = 16
    angles_deg = [...]             # explicit mirror angles, one per line (distinct)
    settle_timeout_s = 10.0

    [camera]
    exposure_s = 0.01
    frames_per_line = 1            # frames acquired (and later averaged) per scan line
    time_range = 1                 # the streak unit's time range: a synchroscan setting number (1),
                                   # or a single-sweep time such as "1 ns"
    gain = 0                       # optional; omitted = leave the camera's gain alone
    acquire_timeout_s = 10.0

    [sync]
    trigger_delay_ps = 0.0
    repetition_rate_hz = 80e6
    channel = 1
    reference = false              # optional: record, for every frame, the sync unit's measured
                                   # interval of the camera trigger after its laser pulse (the run
                                   # store's ``trigger_interval_ps``), a time base that
                                   # ``streaklab reconstruct`` aligns the frames on

    [dark]
    frames = 4                     # dark frames taken with the sync output off (0 = none)

    [calibration]
    time_source = "auto"           # row times for reconstruction: "camera" (the camera's scaling
                                   # table, recorded at capture), "config" (time_poly_ps), or "auto"
                                   # (the table when the run has one, else time_poly_ps)
    time_poly_ps = [0.0, 2.0]      # t(row) = sum_k c_k row**k in ps, row = streak pixel row
                                   # (required unless time_source = "camera")
    time_bin_ps = 2.0              # uniform time bin of the reconstructed cube
    t0_ps = ...                    # optional: time of the first cube bin (default: first
                                   # multiple of time_bin_ps inside the calibrated range)

    [output]
    path = "run.zarr"              # run store (``--out`` overrides it)

    [session]
    retries = 3                    # attempts per line after the first, on a device fault (0..20)
    retry_backoff_s = 0.5          # wait before retry k: retry_backoff_s * 2**k, at most 60 s each
                                   # and 600 s for all retries of one step together

    [simulation]
    seed = 0                       # seed of the simulated lab used by ``--simulate``
    n_x = 64                       # simulated camera: slit pixels
    n_t = 256                      # simulated camera: streak rows
    scene = "default"              # optional: "default" (the table-top scene), "calibration"
                                   # (a flat mirror: one direct return per pixel, for calibrate-irf)
                                   # or "etalon" (a pulse pair per pixel whose arrival steps from
                                   # line to line, for calibrate-sweep) or "uniform" (light of
                                   # one level at every time, for calibrate-shading)
    etalon_ps = 20.0               # optional: the "etalon" scene's pulse separation, ps
    response = "gaussian"          # optional: the simulated camera's instrument response,
                                   # "gaussian", "tailed" (diffusion tail) or "afterpulse"
    jitter_ps = 0.0                # optional: trigger jitter, ps RMS per frame
    drift_ps_per_min = 0.0         # optional: trigger drift, ps per simulated minute
    sweep_nonlinearity = 0.0       # optional: the sweep's quadratic bow, fraction of the window (|n| < 0.25)
    shading = 0.0                  # optional: sensitivity ramp 1 +- shading along the time axis (0 <= s < 1)
    clock_speed = 1.0              # optional: simulated seconds per wall-clock second (the drift's clock)
    fiducial = false               # optional: a fiducial pulse in every frame (drivers.sim.timebase);
                                   # a capture records its nominal position in the run store's
                                   # ``fiducial`` attribute
    reference_noise_ps = 0.5       # optional: RMS noise of the simulated sync unit's trigger-interval
                                   # measurement, ps (read when sync.reference = true)

Sizes and waits are bounded by the documented limits of :mod:`core.limits` (at most
100 000 scan lines, every ``*_timeout_s`` and ``exposure_s`` at most 86 400 s, the retry
waits above).  Unknown sections and keys, wrong types and out-of-range values raise
:class:`ConfigError` whose message starts with the dotted key, e.g.
``scan.count: must be a positive integer, got 0``.
"""
from __future__ import annotations

import copy
import functools
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core import limits as L
from core.errors import StreaklabError

__all__ = ["ConfigError", "ScanConfig", "load_config", "parse_config", "calibration_times_ps",
           "check_calibration", "check_row_times", "HASHED_SECTIONS", "TIME_SOURCES", "SIMULATION_TIMEBASE_KEYS"]


class ConfigError(StreaklabError, ValueError):
    """A configuration value is missing, unknown or out of range; the message names the key."""


# Sections whose values determine the acquired bytes: resuming a run with any of them changed is
# refused.  [devices] (addresses change between sessions, e.g. a simulated lab's ephemeral ports),
# [output] (--out overrides it) and [session] (retry policy) may change between sessions.
HASHED_SECTIONS = ("scan", "camera", "sync", "dark", "calibration", "simulation")

_MISSING = object()


def _fail(key, message):
    raise ConfigError(f"{key}: {message}")


def _is_int(v):
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v):
    return (isinstance(v, (int, float)) and not isinstance(v, bool))


def _num(key, v, *, lo=None, hi=None, lo_open=False, what="a number"):
    if not _is_num(v) or not math.isfinite(v):
        _fail(key, f"must be {what}, got {v!r}")
    v = float(v)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        _fail(key, f"must be {what}, got {v!r}")
    if hi is not None and v > hi:
        _fail(key, f"must be {what}, got {v!r}")
    return v


def _int(key, v, *, lo=None, hi=None, what="an integer"):
    if not _is_int(v) or (lo is not None and v < lo) or (hi is not None and v > hi):
        _fail(key, f"must be {what}, got {v!r}")
    return int(v)


def _str(key, v, *, allow_empty=False):
    if not isinstance(v, str) or (not allow_empty and not v.strip()):
        _fail(key, f"must be a non-empty string, got {v!r}")
    return v


def _choice(key, v, names):
    from drivers.sim import scene

    known = getattr(scene, names)
    if v not in known:
        _fail(key, f"must be one of {', '.join(repr(n) for n in known)}, got {v!r}")
    return v


def _bool(key, v):
    if not isinstance(v, bool):
        _fail(key, f"must be true or false, got {v!r}")
    return v


def _host_port(key, v):
    v = _str(key, v)
    host, sep, port = v.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65535:
        _fail(key, f"must be 'host:port' with a port in 1..65534, got {v!r}")
    return v


def _section(cfg, name, spec, *, required=()):
    """Check one section: no unknown keys, each key validated by its checker."""
    raw = cfg.get(name, {})
    if not isinstance(raw, dict):
        _fail(name, f"must be a table ([{name}]), got {type(raw).__name__}")
    unknown = sorted(set(raw) - set(spec))
    if unknown:
        _fail(f"{name}.{unknown[0]}", f"unknown key (known keys: {', '.join(spec)})")
    out = {}
    for key, (check, default) in spec.items():
        dotted = f"{name}.{key}"
        if key in raw:
            out[key] = check(dotted, raw[key])
        elif key in required:
            _fail(dotted, "is required")
        elif default is not _MISSING:
            out[key] = copy.deepcopy(default)
    return out


def _positive(what="a positive number"):
    return lambda k, v: _num(k, v, lo=0.0, lo_open=True, what=what)


def _seconds(key, v):
    """A positive time in seconds, at most limits.MAX_TIMEOUT_S (a wait that long is a mistake)."""
    return _num(key, v, lo=0.0, lo_open=True, hi=L.MAX_TIMEOUT_S,
                what=f"a positive number of seconds, at most {L.MAX_TIMEOUT_S:g} (limits.MAX_TIMEOUT_S)")


def _line_count(key, v):
    v = _int(key, v, lo=1, what="a positive integer")
    if v > L.MAX_SCAN_LINES:
        _fail(key, f"{v} lines exceeds the limit of {L.MAX_SCAN_LINES} lines (limits.MAX_SCAN_LINES)")
    return v


def _angle_list(key, v):
    if not isinstance(v, list) or not v:
        _fail(key, f"must be a non-empty list of angles in degrees, got {v!r}")
    _line_count(key, len(v))
    out = [_num(f"{key}[{i}]", a, lo=-360.0, hi=360.0, what="an angle in degrees in [-360, 360]")
           for i, a in enumerate(v)]
    if len(set(out)) != len(out):
        dup = next(a for a in out if out.count(a) > 1)
        _fail(key, f"angles must be distinct (each is one scan line), {dup} appears twice")
    return out


def _time_range(key, v):
    from drivers.remoteex_wire import normalize_time_range

    if isinstance(v, bool) or not isinstance(v, (int, str)):
        _fail(key, f"must be a setting number (synchroscan) or a time such as \"1 ns\" (single sweep), got {v!r}")
    try:
        return normalize_time_range(v)
    except ValueError:
        _fail(key, f"must be a setting number (synchroscan) or a time such as \"1 ns\" (single sweep), got {v!r}")


TIME_SOURCES = ("auto", "camera", "config")


def _time_source(key, v):
    if v not in TIME_SOURCES:
        _fail(key, f"must be one of {', '.join(repr(t) for t in TIME_SOURCES)}, got {v!r}")
    return v


def _poly(key, v):
    if not isinstance(v, list) or not v:
        _fail(key, f"must be a non-empty list of polynomial coefficients [c0, c1, ...] in ps, got {v!r}")
    coeffs = [_num(f"{key}[{i}]", c, what="a finite number") for i, c in enumerate(v)]
    if len(coeffs) < 2 or all(c == 0 for c in coeffs[1:]):
        _fail(key, "must depend on the row (a constant calibration maps every row to the same time)")
    return coeffs


def _sweep_nonlinearity(key, v):
    from drivers.sim.timebase import MAX_SWEEP_NONLINEARITY as m

    v = _num(key, v, what=f"a fraction of the window in (-{m:g}, {m:g})")
    if not abs(v) < m:
        _fail(key, f"must be a fraction of the window in (-{m:g}, {m:g}) (the sweep must keep increasing), "
                   f"got {v!r}")
    return v


def _shading(key, v):
    v = _num(key, v, lo=0.0, what="a number in [0, 1)")
    if v >= 1.0:
        _fail(key, f"must be a number in [0, 1), got {v!r}")
    return v


_SPEC = {
    "devices": {
        "camera": (_host_port, "127.0.0.1:1001"),
        "mirror": (_str, "/dev/ttyUSB0"),
        "mirror_address": (lambda k, v: _int(k, v, lo=1, hi=31, what="an integer in 1..31"), 1),
        "mirror_xonxoff": (_bool, True),
        "sync_vendor_id": (lambda k, v: _int(k, v, lo=0, hi=0xFFFF, what="a USB id in 0..0xFFFF"), _MISSING),
        "sync_product_id": (lambda k, v: _int(k, v, lo=0, hi=0xFFFF, what="a USB id in 0..0xFFFF"), _MISSING),
        "sync_serial": (_str, _MISSING),
        "timeout_s": (_seconds, 5.0),
    },
    "scan": {
        "start_deg": (lambda k, v: _num(k, v, lo=-360.0, hi=360.0, what="an angle in [-360, 360] deg"), _MISSING),
        "stop_deg": (lambda k, v: _num(k, v, lo=-360.0, hi=360.0, what="an angle in [-360, 360] deg"), _MISSING),
        "count": (_line_count, _MISSING),
        "angles_deg": (_angle_list, _MISSING),
        "settle_timeout_s": (_seconds, 10.0),
    },
    "camera": {
        "exposure_s": (_seconds, 0.01),
        "frames_per_line": (lambda k, v: _int(k, v, lo=1, hi=10000, what="an integer in 1..10000"), 1),
        "time_range": (_time_range, 1),
        "gain": (lambda k, v: _int(k, v, lo=0, what="a non-negative integer"), _MISSING),
        "acquire_timeout_s": (_seconds, 10.0),
    },
    "sync": {
        "trigger_delay_ps": (lambda k, v: _num(k, v, lo=0.0, hi=1e12, what="a delay in ps in [0, 1e12]"), 0.0),
        "repetition_rate_hz": (_positive("a positive rate in Hz"), 80e6),
        "channel": (lambda k, v: _int(k, v, lo=1, hi=16, what="a channel number in 1..16"), 1),
        # Optional and without a filled-in default, so the hash of configs that do not name it is unchanged.
        "reference": (_bool, _MISSING),
    },
    "dark": {
        "frames": (lambda k, v: _int(k, v, lo=0, hi=10000, what="an integer in 0..10000"), 4),
    },
    "calibration": {
        # No default filled in: configurations that do not name it keep their hash ("auto").
        "time_source": (_time_source, _MISSING),
        "time_poly_ps": (_poly, _MISSING),
        "time_bin_ps": (lambda k, v: _num(k, v, lo=0.0, lo_open=True, hi=1e6,
                                          what="a positive bin width in ps, at most 1e6"), 2.0),
        "t0_ps": (lambda k, v: _num(k, v, what="a finite time in ps"), _MISSING),
    },
    "output": {
        "path": (_str, _MISSING),
    },
    "session": {
        "retries": (lambda k, v: _int(k, v, lo=0, hi=L.MAX_RETRIES,
                                      what=f"an integer in 0..{L.MAX_RETRIES} (limits.MAX_RETRIES)"), 3),
        "retry_backoff_s": (lambda k, v: _num(k, v, lo=0.0, hi=L.MAX_BACKOFF_WAIT_S,
                                              what=f"a number of seconds in [0, {L.MAX_BACKOFF_WAIT_S:g}] "
                                                   f"(limits.MAX_BACKOFF_WAIT_S)"), 0.5),
    },
    "simulation": {
        "seed": (lambda k, v: _int(k, v, lo=0, what="a non-negative integer"), 0),
        "n_x": (lambda k, v: _int(k, v, lo=1, hi=4096, what="an integer in 1..4096"), 64),
        "n_t": (lambda k, v: _int(k, v, lo=16, hi=4096, what="an integer in 16..4096"), 256),
        # Optional and without a filled-in default, so the hash of configs that do not name them is unchanged.
        "scene": (lambda k, v: _choice(k, v, "SIMULATED_SCENES"), _MISSING),
        "response": (lambda k, v: _choice(k, v, "SIMULATED_RESPONSES"), _MISSING),
        "etalon_ps": (lambda k, v: _num(k, v, lo=0.1, hi=1e5, what="a pulse separation in ps in [0.1, 1e5]"), _MISSING),
        # The simulated camera's time base (drivers.sim.timebase); all off when not named.
        "jitter_ps": (lambda k, v: _num(k, v, lo=0.0, hi=1e6, what="a jitter RMS in ps in [0, 1e6]"), _MISSING),
        "drift_ps_per_min": (lambda k, v: _num(k, v, lo=-1e6, hi=1e6, what="a drift in ps per minute in "
                                                                         "[-1e6, 1e6]"), _MISSING),
        "sweep_nonlinearity": (_sweep_nonlinearity, _MISSING),
        "shading": (_shading, _MISSING),
        "clock_speed": (lambda k, v: _num(k, v, lo=0.0, lo_open=True, hi=1e6,
                                          what="a positive clock speed (simulated s per wall s), at most 1e6"),
                        _MISSING),
        "fiducial": (_bool, _MISSING),
        "reference_noise_ps": (lambda k, v: _num(k, v, lo=0.0, hi=1e6, what="a noise RMS in ps in [0, 1e6]"),
                               _MISSING),
    },
}

# Keys of [simulation] that configure the simulated camera's time base (drivers.sim.timebase.TimeBase).
SIMULATION_TIMEBASE_KEYS = ("jitter_ps", "drift_ps_per_min", "sweep_nonlinearity", "shading", "clock_speed",
                            "fiducial")


@dataclass(frozen=True)
class ScanConfig:
    """A validated scan configuration.

    Attributes
    ----------
    data : dict
        The normalised configuration: every section and key, defaults filled
        in, plain JSON types.  ``scan.angles_deg`` always holds the line angles
        (start_deg/stop_deg/count are expanded into it).
    source : str or None
        The file it was read from.
    """

    data: dict
    source: str | None = None

    @property
    def angles_deg(self) -> np.ndarray:
        """Target mirror angle of each scan line, shape (n_lines,), degrees, in acquisition order."""
        return np.asarray(self.data["scan"]["angles_deg"], dtype=np.float64)

    @property
    def n_lines(self) -> int:
        return len(self.data["scan"]["angles_deg"])

    def __getitem__(self, section: str) -> dict:
        return self.data[section]

    def hashed_part(self) -> dict:
        return {k: self.data[k] for k in HASHED_SECTIONS}

    @property
    def hash(self) -> str:
        """sha256 of the canonical JSON of the sections that determine the acquired data."""
        text = json.dumps(self.hashed_part(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()


def parse_config(raw: dict, *, source: str | None = None) -> ScanConfig:
    """Validate a configuration dict (as parsed from TOML) and fill in defaults.

    Raises
    ------
    ConfigError
        Naming the first offending key.
    """
    if not isinstance(raw, dict):
        raise ConfigError(f"configuration must be a table, got {type(raw).__name__}")
    unknown = sorted(set(raw) - set(_SPEC))
    if unknown:
        _fail(unknown[0], f"unknown section (known sections: {', '.join(_SPEC)})")
    data = {name: _section(raw, name, spec) for name, spec in _SPEC.items()}

    dev = data["devices"]
    has_ids = [k in dev for k in ("sync_vendor_id", "sync_product_id")]
    if any(has_ids) and not all(has_ids):
        missing = "sync_product_id" if has_ids[0] else "sync_vendor_id"
        _fail(f"devices.{missing}", "is required together with the other USB id")

    scan = data["scan"]
    ranged = [k for k in ("start_deg", "stop_deg", "count") if k in scan]
    if "angles_deg" in scan:
        if ranged:
            _fail(f"scan.{ranged[0]}", "give either angles_deg or start_deg/stop_deg/count, not both")
    else:
        for k in ("start_deg", "stop_deg", "count"):
            if k not in scan:
                _fail(f"scan.{k}", "is required (or give an explicit scan.angles_deg list)")
        if scan["count"] > 1 and scan["start_deg"] == scan["stop_deg"]:
            _fail("scan.stop_deg", "must differ from start_deg when count > 1 (lines would coincide)")
        scan["angles_deg"] = [float(a) for a in np.linspace(scan["start_deg"], scan["stop_deg"], scan["count"])]
        for k in ("start_deg", "stop_deg", "count"):   # normalised form: the explicit angle list only
            del scan[k]
    sess = data["session"]
    total = sum(L.backoff_waits(sess["retries"], sess["retry_backoff_s"]))
    if total > L.MAX_BACKOFF_TOTAL_S:
        _fail("session.retries", f"{sess['retries']} retries with retry_backoff_s = {sess['retry_backoff_s']:g} "
                                 f"wait {total:g} s in all, above the limit of {L.MAX_BACKOFF_TOTAL_S:g} s "
                                 f"(limits.MAX_BACKOFF_TOTAL_S); use fewer retries or a shorter back-off")
    if "time_poly_ps" not in data["calibration"] and data["calibration"].get("time_source", "auto") != "camera":
        _fail("calibration.time_poly_ps", "is required (pixel row -> ps polynomial of the streak sweep) unless "
                                          "calibration.time_source = \"camera\"")
    return ScanConfig(data=data, source=source)


# Configurations installed with the package, by the name ``--config`` accepts for them.
EXAMPLE_CONFIGS = {"sim": "sim_scan.toml"}


def example_config_path(name: str = "sim") -> Path:
    """The packaged example configuration ``name`` (see EXAMPLE_CONFIGS)."""
    if name not in EXAMPLE_CONFIGS:
        raise ConfigError(f"no example configuration {name!r}; available: {', '.join(EXAMPLE_CONFIGS)}")
    return Path(__file__).resolve().parent / "examples" / EXAMPLE_CONFIGS[name]


def simulated_example_address(config: ScanConfig, device: str) -> bool:
    """True when ``devices.<device>`` is the packaged simulated-lab example's placeholder address,
    not a rig's: the config is the packaged example itself, or the address is the example's
    loopback camera address (a copy written by ``streaklab example-config``).  A capture that
    cannot reach such a device was meant for ``--simulate``."""
    if config.source is not None:
        try:
            if Path(config.source).resolve() == example_config_path("sim"):
                return True
        except OSError:
            pass
    return device == "camera" and config["devices"].get("camera") == _example_devices().get("camera")


@functools.lru_cache(maxsize=1)
def _example_devices() -> dict:
    with open(example_config_path("sim"), "rb") as f:
        return dict(tomllib.load(f).get("devices", {}))


def resolve_config_path(path) -> Path:
    """``path`` itself, or the packaged example when ``path`` is one of its names (``sim``) and no
    file of that name exists."""
    p = Path(path)
    if str(path) in EXAMPLE_CONFIGS and not p.exists():
        return example_config_path(str(path))
    return p


def load_config(path) -> ScanConfig:
    """Read and validate a TOML scan configuration file (or a packaged example, by name: ``sim``)."""
    p = resolve_config_path(path)
    try:
        with open(p, "rb") as f:
            text = f.read(L.MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        hint = ("; 'sim' names the packaged example of the simulated lab, and 'streaklab example-config --out "
                "scan.toml' writes a copy to edit" if isinstance(exc, FileNotFoundError) else "")
        raise ConfigError(f"{path}: cannot read the configuration: {exc.strerror or exc}{hint}") from None
    if len(text) > L.MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: the configuration is larger than the limit of "
                          f"{L.format_bytes(L.MAX_CONFIG_BYTES)} (limits.MAX_CONFIG_BYTES)")
    try:
        raw = tomllib.loads(text.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"{path}: not valid TOML: arrays or tables nested too deeply") from None
    return parse_config(raw, source=str(p))


def calibration_times_ps(time_poly_ps, n_rows: int) -> np.ndarray:
    """Time of each streak pixel row from the calibration polynomial.

    Parameters
    ----------
    time_poly_ps : sequence of float
        Coefficients c_k of t(row) = sum_k c_k row**k, in ps (increasing powers).
    n_rows : int
        Number of pixel rows on the streak (time) axis.

    Returns
    -------
    ndarray, shape (n_rows,), float64, ps.
    """
    rows = np.arange(int(n_rows), dtype=np.float64)
    return np.polynomial.polynomial.polyval(rows, np.asarray(time_poly_ps, dtype=np.float64))


def check_calibration(time_poly_ps, n_rows: int, *, key: str = "calibration.time_poly_ps") -> np.ndarray:
    """Row times, after checking that they are finite and strictly monotonic over all rows.

    Raises
    ------
    ConfigError
        Naming the key and the first row where monotonicity fails.
    """
    return check_row_times(calibration_times_ps(time_poly_ps, n_rows), n_rows, key=key)


def check_row_times(t, n_rows: int, *, key: str) -> np.ndarray:
    """Row times (polynomial or camera table) checked: one per row, finite, strictly monotonic.

    Raises
    ------
    ConfigError
        Naming the key and the first row where monotonicity fails.
    """
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (n_rows,):
        raise ConfigError(f"{key}: holds {t.size} row times but the streak axis has {n_rows} rows")
    if n_rows < 2:
        raise ConfigError(f"{key}: the streak axis needs at least 2 rows, got {n_rows}")
    if not np.all(np.isfinite(t)):
        raise ConfigError(f"{key}: gives non-finite times over rows 0..{n_rows - 1}")
    d = np.diff(t)
    if not (np.all(d > 0) or np.all(d < 0)):
        sign = np.sign(d[0]) if d[0] != 0 else 1.0
        bad = int(np.flatnonzero(np.sign(d) != sign)[0])
        raise ConfigError(
            f"{key}: must be strictly monotonic over rows 0..{n_rows - 1}, but t(row {bad}) = {t[bad]:.6g} ps "
            f"and t(row {bad + 1}) = {t[bad + 1]:.6g} ps")
    return t
