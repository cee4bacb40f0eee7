"""``streaklab capture --live``: lines decomposed as they land, equal to the offline decomposition."""
import numpy as np
import pytest
import zarr

from tests.test_capture_resume import write_config

N_LINES, N_X = 4, 16


def _assert_same_arrays(a, b):
    """Every array of two result stores (the ``irf`` group too), byte for byte."""
    from streaklab.live_decompose import differing_arrays

    assert differing_arrays(a, b) == []


def _offline(tmp_path, run, name="offline.zarr"):
    """``streaklab reconstruct`` then ``streaklab decompose --per-pixel --chunks 1 NX`` of the run."""
    from streaklab.cli import main

    assert main(["reconstruct", str(run), "--out", str(tmp_path / "cube.zarr")]) == 0
    assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", str(tmp_path / name),
                 "--chunks", "1", str(N_X), "--quiet", "--per-pixel"]) == 0
    return tmp_path / name


def _capture(tmp_path, *extra):
    from streaklab.cli import main

    return main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "run.zarr"),
                 "--simulate", *extra])


@pytest.mark.timeout(120)
def test_live_result_equals_the_offline_decomposition_shows_progress_and_resumes(tmp_path, capsys,
                                                                                 live_worker_at_normal_priority):
    from decomposition.store.resultstore import open_result_store

    write_config(tmp_path / "scan.toml", n_lines=N_LINES)
    live, png = tmp_path / "live.zarr", tmp_path / "maps.png"
    assert _capture(tmp_path, "--live", str(live), "--live-png", str(png), "--live-png-every", "2") == 0
    err = capsys.readouterr().err
    assert f"capture: {N_LINES}/{N_LINES} lines" in err and "decomposed " in err
    assert f"live result {live}: decomposed {N_LINES}/{N_LINES} lines" in err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not (tmp_path / "maps.png.tmp.png").exists()
    store = open_result_store(live)
    assert store.done_mask().all() and tuple(store.chunks) == (1, N_X)
    assert store.attrs["options"]["signal_noise_law"] == "detector"      # the cube's noise law
    offline = _offline(tmp_path, tmp_path / "run.zarr")
    _assert_same_arrays(live, offline)

    # as if killed before two lines were decomposed: a resume decomposes just those again
    store = open_result_store(live, mode="r+")
    store.mark_chunks_not_done([(1, 0), (3, 0)])
    assert _capture(tmp_path, "--resume", "--live", str(live)) == 0
    err = capsys.readouterr().err
    assert f"resuming {tmp_path / 'run.zarr'}: {N_LINES} of {N_LINES} lines already on disk" in err
    assert f"live result {live}: decomposed {N_LINES}/{N_LINES} lines" in err
    _assert_same_arrays(live, offline)


@pytest.mark.timeout(120)
def test_an_interrupted_live_capture_resumes_to_the_same_result(tmp_path, monkeypatch, capsys,
                                                                live_worker_at_normal_priority):
    import acquisition.rig as rig
    from decomposition.store.resultstore import open_result_store

    write_config(tmp_path / "scan.toml", n_lines=N_LINES)
    real = rig.run_capture

    def aborted_after_two_lines(config, out, **kw):
        def on_line(session, line):
            kw["on_line"](session, line)
            if session.lines_done() == 2:
                raise KeyboardInterrupt            # a second Ctrl-C: the capture is abandoned there
        return real(config, out, **{**kw, "on_line": on_line})

    live = tmp_path / "live.zarr"
    monkeypatch.setattr(rig, "run_capture", aborted_after_two_lines)
    assert _capture(tmp_path, "--live", str(live), "--quiet") == 130
    err = capsys.readouterr().err
    assert f"--live {live}" in err and "--resume" in err            # the resume hint keeps --live
    done = open_result_store(live).done_mask().all(axis=1)
    assert done.sum() <= 2                                           # whole lines only, at most those captured
    monkeypatch.setattr(rig, "run_capture", real)
    assert _capture(tmp_path, "--resume", "--live", str(live), "--quiet") == 0
    assert f"decomposed {N_LINES}/{N_LINES} lines" in capsys.readouterr().err
    _assert_same_arrays(live, _offline(tmp_path, tmp_path / "run.zarr"))


@pytest.mark.timeout(60)
def test_the_live_worker_runs_at_the_lowest_priority(tmp_path):
    import os

    from streaklab.live_decompose import LiveDecomposition

    live = LiveDecomposition(tmp_path / "live.zarr")
    live.launch()
    try:
        # the lowest nice level, not SCHED_IDLE: that would never run on a machine whose every core is busy
        assert os.getpriority(os.PRIO_PROCESS, live._proc.pid) == 19
        if hasattr(os, "sched_getscheduler"):
            assert os.sched_getscheduler(live._proc.pid) == os.SCHED_OTHER
    finally:
        live._proc.kill()                  # not close(): at that priority a busy machine slows its end
        live._proc.join(10)
    assert not live.alive()


def test_live_refuses_an_occupied_store_before_any_device_is_opened(tmp_path, capsys):
    from streaklab.cli import main

    write_config(tmp_path / "scan.toml", n_lines=N_LINES)
    (tmp_path / "live.zarr").mkdir()
    (tmp_path / "live.zarr" / "notes.txt").write_text("mine")
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "run.zarr"),
                 "--simulate", "--live", str(tmp_path / "live.zarr")]) == 2
    assert "--live" in capsys.readouterr().err
    assert not (tmp_path / "run.zarr").exists() and (tmp_path / "live.zarr" / "notes.txt").exists()
    assert main(["capture", "--config", str(tmp_path / "scan.toml"), "--out", str(tmp_path / "run.zarr"),
                 "--simulate", "--live-png", str(tmp_path / "m.png")]) == 2


def test_differing_arrays_names_each_array_not_the_same_byte_for_byte(tmp_path):
    import shutil

    from streaklab.live_decompose import differing_arrays

    g = zarr.open_group(str(tmp_path / "a.zarr"), mode="w")
    g.create_array("delay_ps", data=np.array([1.0, np.nan, 3.0], np.float32))
    g.create_group("irf").create_array("samples", data=np.arange(4.0))
    shutil.copytree(tmp_path / "a.zarr", tmp_path / "b.zarr")
    assert differing_arrays(tmp_path / "a.zarr", tmp_path / "b.zarr") == []      # NaN where NaN is the same
    b = zarr.open_group(str(tmp_path / "b.zarr"), mode="r+")
    b["irf"]["samples"][2] = 2.0 + 1e-12                     # one value off in a nested group
    b.create_array("extra", data=np.zeros(2))
    assert differing_arrays(tmp_path / "a.zarr", tmp_path / "b.zarr") == [
        f"extra (only in {tmp_path / 'b.zarr'})", "irf/samples (bytes differ)"]
