"""Scan configuration: TOML parsing, defaults, and errors that name the offending key."""
from pathlib import Path

import numpy as np
import pytest

from acquisition.config import ConfigError, check_calibration, load_config, parse_config

BASE = {"scan": {"start_deg": -2.0, "stop_deg": 2.0, "count": 5},
        "calibration": {"time_poly_ps": [0.0, 2.0, 0.001]}}


def cfg(**sections):
    raw = {k: dict(v) for k, v in BASE.items()}
    for name, values in sections.items():
        raw.setdefault(name, {}).update(values)
    return raw


def test_defaults_and_line_angles():
    c = parse_config(cfg())
    np.testing.assert_allclose(c.angles_deg, [-2, -1, 0, 1, 2])
    assert c.n_lines == 5
    assert c["camera"]["frames_per_line"] == 1 and c["dark"]["frames"] == 4
    assert c["calibration"]["time_bin_ps"] == 2.0 and "t0_ps" not in c["calibration"]
    assert c["session"]["retries"] == 3
    assert c["devices"]["mirror_xonxoff"] is True     # SMC100 manual: Xon/Xoff flow control
    assert parse_config(cfg(devices={"mirror_xonxoff": False}))["devices"]["mirror_xonxoff"] is False


def test_explicit_angle_list():
    c = parse_config({"scan": {"angles_deg": [3, 1.5, -1]}, "calibration": BASE["calibration"]})
    np.testing.assert_allclose(c.angles_deg, [3, 1.5, -1])


@pytest.mark.parametrize("sections, message", [
    ({"scan": {"count": 0}}, r"^scan\.count: must be a positive integer, got 0$"),
    ({"scan": {"count": 2.5}}, r"^scan\.count: must be a positive integer"),
    ({"scan": {"count": True}}, r"^scan\.count: must be a positive integer"),
    ({"scan": {"bogus": 1}}, r"^scan\.bogus: unknown key"),
    ({"scna": {}}, r"^scna: unknown section"),
    ({"camera": {"exposure_s": -0.1}}, r"^camera\.exposure_s: must be a positive number of seconds"),
    ({"camera": {"exposure_s": "fast"}}, r"^camera\.exposure_s:"),
    ({"camera": {"frames_per_line": 0}}, r"^camera\.frames_per_line:"),
    ({"dark": {"frames": -1}}, r"^dark\.frames:"),
    ({"sync": {"trigger_delay_ps": -5.0}}, r"^sync\.trigger_delay_ps:"),
    ({"sync": {"repetition_rate_hz": 0}}, r"^sync\.repetition_rate_hz:"),
    ({"devices": {"camera": "localhost"}}, r"^devices\.camera: must be 'host:port'"),
    ({"devices": {"camera": "localhost:99999"}}, r"^devices\.camera:"),
    ({"devices": {"mirror_xonxoff": 1}}, r"^devices\.mirror_xonxoff: must be true or false, got 1$"),
    ({"devices": {"sync_vendor_id": 0x1234}}, r"^devices\.sync_product_id: is required together"),
    ({"devices": {"sync_vendor_id": 0x12345, "sync_product_id": 1}}, r"^devices\.sync_vendor_id:"),
    ({"calibration": {"time_bin_ps": 0}}, r"^calibration\.time_bin_ps:"),
    ({"calibration": {"time_poly_ps": [5.0]}}, r"^calibration\.time_poly_ps: must depend on the row"),
    ({"calibration": {"time_poly_ps": []}}, r"^calibration\.time_poly_ps:"),
    ({"session": {"retries": -1}}, r"^session\.retries:"),
    ({"scan": {"angles_deg": [1, 2]}}, r"^scan\.start_deg: give either angles_deg"),
])
def test_bad_values_name_the_key(sections, message):
    with pytest.raises(ConfigError, match=message):
        parse_config(cfg(**sections))


def test_missing_and_inconsistent_scan_keys():
    with pytest.raises(ConfigError, match=r"^scan\.count: is required"):
        parse_config({"scan": {"start_deg": 0, "stop_deg": 1}, "calibration": BASE["calibration"]})
    with pytest.raises(ConfigError, match=r"^scan\.angles_deg: angles must be distinct"):
        parse_config({"scan": {"angles_deg": [1, 2, 1]}, "calibration": BASE["calibration"]})
    with pytest.raises(ConfigError, match=r"^scan\.angles_deg\[1\]:"):
        parse_config({"scan": {"angles_deg": [1, "x"]}, "calibration": BASE["calibration"]})
    with pytest.raises(ConfigError, match=r"^scan\.stop_deg: must differ"):
        parse_config(cfg(scan={"start_deg": 1.0, "stop_deg": 1.0}))
    with pytest.raises(ConfigError, match=r"^calibration\.time_poly_ps: is required"):
        parse_config({"scan": BASE["scan"]})


def test_hash_covers_acquisition_not_addresses():
    a = parse_config(cfg())
    assert a.hash == parse_config(cfg(devices={"camera": "10.0.0.2:1001"}, output={"path": "x.zarr"},
                                      session={"retries": 7})).hash
    assert a.hash != parse_config(cfg(camera={"exposure_s": 0.02})).hash
    assert a.hash != parse_config(cfg(scan={"count": 6})).hash
    assert a.hash != parse_config(cfg(simulation={"seed": 1})).hash


def test_toml_file_and_example(tmp_path):
    p = tmp_path / "scan.toml"
    p.write_text('[scan]\nangles_deg = [0.5, 1.5]\n[calibration]\ntime_poly_ps = [1.0, 2.0]\n'
                 '[devices]\nsync_vendor_id = 0x0699\nsync_product_id = 0x0346\n')
    c = load_config(p)
    assert c["devices"]["sync_vendor_id"] == 0x0699 and c.source == str(p)
    (tmp_path / "bad.toml").write_text("[scan\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(tmp_path / "bad.toml")
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
    example = load_config(Path(__file__).resolve().parents[1] / "acquisition/examples/sim_scan.toml")
    assert example.n_lines >= 2


def test_calibration_monotonic_check():
    t = check_calibration([0.0, 2.0, 0.001], 100)
    assert t.shape == (100,) and np.all(np.diff(t) > 0)
    assert np.all(np.diff(check_calibration([500.0, -2.0], 100)) < 0)  # decreasing is fine
    with pytest.raises(ConfigError, match=r"strictly monotonic over rows 0\.\.99.*row 49"):
        check_calibration([0.0, 2.0, -0.0204], 100)


@pytest.mark.parametrize("sections, message", [
    # one scan line per angle: 1e9 lines would be a 7.45 GiB angle list before anything is checked
    ({"scan": {"count": 10**9}}, r"^scan\.count: 1000000000 lines exceeds the limit of 100000 lines"),
    ({"scan": {"count": 2**63 - 1}}, r"^scan\.count: 9223372036854775807 lines exceeds the limit of 100000"),
    ({"devices": {"timeout_s": 1e308}}, r"^devices\.timeout_s: must be a positive number of seconds, at most 86400"),
    ({"camera": {"acquire_timeout_s": 1e6}}, r"^camera\.acquire_timeout_s: .*at most 86400"),
    ({"scan": {"settle_timeout_s": 1e20}}, r"^scan\.settle_timeout_s: .*at most 86400"),
    ({"session": {"retries": 100}}, r"^session\.retries: must be an integer in 0\.\.20 \(limits\.MAX_RETRIES\)"),
    # 20 retries of 0.5 s doubling, each capped at 60 s: 63.5 + 13 x 60 = 843.5 s of waiting for one step
    ({"session": {"retries": 20}}, r"^session\.retries: 20 retries .* wait 843\.5 s in all, above the limit of 600 s"),
])
def test_sizes_and_waits_are_limited_naming_key_and_limit(sections, message):
    with pytest.raises(ConfigError, match=message):
        parse_config(cfg(**sections))


def test_long_angle_list_and_oversized_or_deeply_nested_files_are_refused(tmp_path):
    with pytest.raises(ConfigError, match=r"^scan\.angles_deg: 100001 lines exceeds the limit of 100000"):
        parse_config({"scan": {"angles_deg": list(range(100_001))}, "calibration": BASE["calibration"]})
    nested = tmp_path / "nested.toml"
    nested.write_text("x = " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ConfigError, match=r"nested\.toml: not valid TOML: arrays or tables nested too deeply$"):
        load_config(nested)
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (1 << 20) + "\n")
    with pytest.raises(ConfigError, match=r"big\.toml: the configuration is larger than the limit of 1\.00 MiB"):
        load_config(big)


def test_time_bin_is_bounded():
    with pytest.raises(ConfigError, match=r"^calibration\.time_bin_ps: must be a positive bin width in ps, at most "
                                          r"1e6, got 1e\+300$"):
        parse_config(cfg(calibration={"time_bin_ps": 1e300}))
