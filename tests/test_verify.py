"""Damaged chunks are found and named: checksums on every array, missing chunks of finished work,
``streaklab verify`` and ``--mark-for-resume``; stores of the previous release still open."""
import numpy as np
import pytest
import zarr

from _cubes import TB, small_cube
from acquisition.rig import run_capture
from acquisition.runstore import open_run
from acquisition.session import CaptureError
from decomposition.store.resultstore import open_result_store
from reconstruction.build import ReconstructionError, reconstruct
from reconstruction.cubestore import write_cube
from streaklab.cli import main
from decomposition.store.pipeline import decompose_to_store
from test_capture import sim_config
from test_reconstruct import make_run


def flip_bit(path, at=0.5):
    data = bytearray(path.read_bytes())
    data[int(len(data) * at)] ^= 0x10
    path.write_bytes(bytes(data))


def test_every_array_is_checksummed(tmp_path):
    run = make_run(tmp_path / "run.zarr")
    cube = reconstruct(run.path, tmp_path / "cube.zarr")
    for store in (run.path, cube.path):
        g = zarr.open_group(str(store), mode="r")
        for name, arr in g.arrays():
            assert any(type(c).__name__ == "Crc32cCodec" for c in arr.metadata.codecs), (store, name)


def test_damaged_run_lines_are_errors_not_numbers(tmp_path, capsys):
    run = make_run(tmp_path / "run.zarr")
    (tmp_path / "run.zarr/streaks/c/2/0/0/0").unlink()
    with pytest.raises(ReconstructionError, match=r"line 2 is marked done but streaks chunks are missing.*"
                                                  r"streaklab verify .* --mark-for-resume"):
        reconstruct(run.path, tmp_path / "cube.zarr")
    make_run(tmp_path / "run2.zarr")
    (tmp_path / "run2.zarr/dark/c/0/0/0").unlink()
    with pytest.raises(ReconstructionError, match="dark frames are marked done but their chunk is missing"):
        reconstruct(tmp_path / "run2.zarr", tmp_path / "cube.zarr")
    make_run(tmp_path / "run3.zarr")
    flip_bit(tmp_path / "run3.zarr/streaks/c/4/0/0/0")
    assert main(["reconstruct", str(tmp_path / "run3.zarr"), "--out", str(tmp_path / "cube.zarr")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "array 'streaks', chunk (4, 0, 0, 0) fails its checksum" in err
    assert not (tmp_path / "cube.zarr").exists()


def test_verify_names_damaged_lines_and_resume_recaptures_just_those(tmp_path, capsys):
    cfg = sim_config(n_lines=4)
    out = tmp_path / "run.zarr"
    assert run_capture(cfg, out, simulate=True).status == "complete"
    before = open_run(out)["streaks"][...]
    assert main(["verify", str(out)]) == 0
    assert "no damage found" in capsys.readouterr().out
    (out / "streaks/c/1/0/0/0").unlink()
    flip_bit(out / "streaks/c/3/0/0/0")
    flipped = (out / "streaks/c/3/0/0/0").read_bytes()
    with pytest.raises(CaptureError, match="line 1 is marked done but streaks chunks are missing"):
        run_capture(cfg, out, simulate=True, resume=True)
    assert main(["verify", str(out)]) == 1
    text = capsys.readouterr().out
    assert "line 1:\n  streaks chunk (1, 0, 0, 0): missing" in text
    assert "line 3:\n  streaks chunk (3, 0, 0, 0): fails its checksum" in text
    assert "--mark-for-resume" in text and "--simulate --resume" in text
    assert main(["verify", str(out), "--mark-for-resume"]) == 1
    assert "marked lines 1, 3 not done" in capsys.readouterr().out
    assert open_run(out).done_mask().tolist() == [True, False, True, False]
    assert (out / "streaks/c/3/0/0/0").read_bytes() == flipped          # flags only: no data deleted
    result = run_capture(cfg, out, simulate=True, resume=True)
    assert result.status == "complete" and result.acquired == [1, 3]
    np.testing.assert_array_equal(open_run(out)["streaks"][...], before)
    assert main(["verify", str(out)]) == 0


def test_result_store_damage_is_found_and_recomputed(tmp_path, capsys):
    write_cube(tmp_path / "cube.zarr", small_cube(2, 3, seed=5), time_bin_ps=TB, chunks=(1, 3))
    res = tmp_path / "res.zarr"
    decompose_to_store(tmp_path / "cube.zarr", res, progress=False)
    good = open_result_store(res).params()
    (res / "direct_delay_ps/c/1/0").unlink()
    assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", str(res), "--resume", "--quiet"]) == 2
    assert "pixel chunk (1, 0) is marked done but direct_delay_ps chunk files are missing" in capsys.readouterr().err
    assert main(["verify", str(res), "--mark-for-resume"]) == 1
    text = capsys.readouterr().out
    assert "pixel chunk (1, 0) (y 1..1, x 0..2):\n  direct_delay_ps chunk (1, 0): missing" in text
    assert "marked 1 pixel chunk not done" in text
    assert open_result_store(res).done_chunks().tolist() == [[True], [False]]
    assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", str(res), "--resume", "--quiet"]) == 0
    again = open_result_store(res).params()
    for k, v in good.items():
        np.testing.assert_array_equal(again[k], v, err_msg=k)
    assert main(["verify", str(res)]) == 0
    # a damaged input chunk stops the decomposition with one line naming it
    flip_bit(tmp_path / "cube.zarr/cube/c/1/0/0")
    assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", str(tmp_path / "r2.zarr"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "array 'cube', chunk (1, 0, 0) fails its checksum" in err
    assert main(["verify", str(tmp_path / "cube.zarr")]) == 1
    text = capsys.readouterr().out
    assert "cube chunk (1, 0, 0): fails its checksum" in text and "(y 1..1, x 0..2)" in text


def test_stores_of_the_previous_release_open_resume_and_verify(tmp_path, monkeypatch, capsys):
    """A run store built the old way (no checksums, fill-only chunks skipped) still resumes and
    reconstructs; verify says it has no checksums instead of failing."""
    import acquisition.runstore as runstore

    monkeypatch.setattr(runstore, "create_array", lambda g, name, **kw: g.create_array(name, **kw))
    monkeypatch.setattr(runstore, "writable", lambda arr: arr)
    cfg = sim_config(n_lines=3)
    out = tmp_path / "old.zarr"
    run = runstore.create_run(out, cfg, image_shape=(16, 64))
    assert not any(type(c).__name__ == "Crc32cCodec" for c in run["streaks"].metadata.codecs)
    monkeypatch.undo()
    assert run_capture(cfg, out, simulate=True, resume=True).status == "complete"
    assert main(["verify", str(out)]) == 0
    text = capsys.readouterr().out
    assert "written without checksums" in text and "no damage found" in text
    reconstruct(out, tmp_path / "cube.zarr")


def test_export_of_a_damaged_cube_names_the_chunk(tmp_path, capsys):
    write_cube(tmp_path / "cube.zarr", small_cube(2, 3, seed=5), time_bin_ps=TB, chunks=(1, 3))
    flip_bit(tmp_path / "cube.zarr/cube/c/1/0/0")
    assert main(["export", str(tmp_path / "cube.zarr"), "--out", str(tmp_path / "c.h5")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "array 'cube', chunk (1, 0, 0) fails its checksum" in err
    assert not (tmp_path / "c.h5").exists()


def test_a_result_store_of_the_previous_release_resumes(tmp_path, monkeypatch, capsys):
    """Built the old way: no checksums, uint8 flags, fill-only chunks not written."""
    import shutil

    import decomposition.store.resultstore as rs

    def old_array(g, name, zstd_level=0, **kw):      # zarr's own codecs: no checksum
        kw = {**kw, "dtype": "uint8"} if name == "flags" else kw
        return g.create_array(name, **kw)

    write_cube(tmp_path / "cube.zarr", small_cube(2, 3, seed=5), time_bin_ps=TB, chunks=(1, 3))
    decompose_to_store(tmp_path / "cube.zarr", tmp_path / "ref.zarr", progress=False)
    monkeypatch.setattr(rs, "create_array", old_array)
    monkeypatch.setattr(rs, "writable", lambda arr: arr)
    res = tmp_path / "old.zarr"
    decompose_to_store(tmp_path / "cube.zarr", res, progress=False)
    monkeypatch.undo()
    g = zarr.open_group(str(res), mode="r+")
    assert g["flags"].dtype == np.uint8
    g["done"][1:2] = False                                   # as if killed after the first chunk
    for name in g.array_keys():
        if name != "done" and (res / name / "c" / "1").exists():
            shutil.rmtree(res / name / "c" / "1")
    assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", str(res), "--resume", "--quiet"]) == 0
    a, b = open_result_store(res).params(), open_result_store(tmp_path / "ref.zarr").params()
    for k in b:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert main(["verify", str(res)]) == 0
    assert "written without checksums" in capsys.readouterr().out


def test_verify_names_a_stopped_capture_incomplete_and_how_to_finish_it(tmp_path, capsys):
    import threading

    cfg = sim_config(n_lines=5)
    out = tmp_path / "run.zarr"
    stop = threading.Event()
    result = run_capture(cfg, out, simulate=True, stop_event=stop,
                         on_line=lambda session, line: stop.set() if session.lines_done() == 2 else None)
    assert result.status != "complete" and result.lines_done == 2
    assert main(["verify", str(out)]) == 0                     # nothing damaged: not an error
    text = capsys.readouterr().out
    assert "incomplete: 2 of 5 lines captured" in text
    assert "no damage found in the captured lines" in text
    assert f"finish the capture with:\n  streaklab capture --config SCAN.toml --out {out} --simulate --resume" in text
    # damage in a stopped run: both, and the one command redoes the damaged line and the rest
    (out / "streaks/c/1/0/0/0").unlink()
    assert main(["verify", str(out)]) == 1
    text = capsys.readouterr().out
    assert "incomplete: 2 of 5 lines captured" in text and "line 1:\n  streaks chunk (1, 0, 0, 0): missing" in text
    assert "to recapture just those and finish the capture:" in text
    # a complete run says neither
    done = tmp_path / "done.zarr"
    assert run_capture(cfg, done, simulate=True).status == "complete"
    assert main(["verify", str(done)]) == 0
    text = capsys.readouterr().out
    assert "incomplete" not in text and text.endswith("no damage found\n")


def test_verify_names_a_stopped_decomposition_incomplete_and_counts_in_words(tmp_path, capsys):
    write_cube(tmp_path / "cube.zarr", small_cube(2, 3, seed=5), time_bin_ps=TB, chunks=(1, 3))
    res = tmp_path / "res.zarr"
    decompose_to_store(tmp_path / "cube.zarr", res, progress=False)
    assert main(["verify", str(res)]) == 0
    assert f"{res}: result store, 2 x 3 pixels in 2 chunks of 1 x 3\nno damage found\n" in capsys.readouterr().out
    zarr.open_group(str(res), mode="r+")["done"][1:2] = False      # as if stopped after the first chunk
    assert main(["verify", str(res)]) == 0
    text = capsys.readouterr().out
    assert "incomplete: 1 of 2 pixel chunks decomposed" in text
    assert (f"finish the decomposition with:\n  streaklab decompose {tmp_path / 'cube.zarr'} --out {res} --resume"
            in text)
    write_cube(tmp_path / "one.zarr", small_cube(1, 3, seed=5), time_bin_ps=TB, chunks=(1, 3))
    decompose_to_store(tmp_path / "one.zarr", tmp_path / "one-res.zarr", progress=False)
    assert main(["verify", str(tmp_path / "one-res.zarr")]) == 0
    assert "result store, 1 x 3 pixels in 1 chunk of 1 x 3\n" in capsys.readouterr().out


def test_verify_of_a_copied_cube_names_the_copy_in_its_command(tmp_path, monkeypatch, capsys):
    import shlex
    import shutil

    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--shape", "2", "3", "64", "--seed", "4", "--chunks", "1", "3",
                 "--out", "orig.zarr"]) == 0
    shutil.copytree("orig.zarr", "copy.zarr")
    flip_bit(tmp_path / "copy.zarr/cube/c/1/0/0")
    assert main(["verify", "copy.zarr"]) == 1
    text = capsys.readouterr().out
    assert "orig.zarr" not in text
    command = text.split("write it again with:\n  ", 1)[1].splitlines()[0]
    argv = shlex.split(command)
    assert argv[:2] == ["streaklab", "simulate"] and argv[-3:] == ["--out", "copy.zarr", "--overwrite"]
    assert main(argv[1:]) == 0                                      # the command rebuilds the copy as it was
    capsys.readouterr()
    np.testing.assert_array_equal(zarr.open_group("copy.zarr", mode="r")["cube"][...],
                                  zarr.open_group("orig.zarr", mode="r")["cube"][...])
    assert main(["verify", "copy.zarr"]) == 0
