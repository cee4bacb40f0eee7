"""Output paths never destroy an input or a store of another kind."""
import numpy as np
import pytest
import zarr

from _cubes import TB, small_cube
from core.staging import OutputPathError, check_output_path, describe_existing
from reconstruction.cubestore import write_cube
from streaklab.cli import main
from test_reconstruct import make_run


def _streaks_bytes(run_path):
    return zarr.open_group(str(run_path), mode="r")["streaks"][...].tobytes()


def test_reconstruct_into_the_run_store_is_refused(tmp_path, capsys):
    run = make_run(tmp_path / "run.zarr")
    before = _streaks_bytes(run.path)
    assert main(["reconstruct", run.path, "--out", f"{run.path}/streaks", "--overwrite"]) == 2
    assert "lies inside the input" in capsys.readouterr().err
    assert _streaks_bytes(run.path) == before
    # a directory holding the run is refused too
    assert main(["reconstruct", run.path, "--out", str(tmp_path), "--overwrite"]) == 2
    assert "holds the input" in capsys.readouterr().err
    assert _streaks_bytes(run.path) == before


def test_decompose_into_the_cube_store_is_refused(tmp_path, capsys):
    data = small_cube(2, 3, seed=1)
    write_cube(tmp_path / "cube.zarr", data, time_bin_ps=TB)
    for extra in (["--overwrite"], ["--resume"]):
        assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", str(tmp_path / "cube.zarr/cube"),
                     "--quiet", *extra]) == 2
        assert "lies inside the input" in capsys.readouterr().err
    np.testing.assert_array_equal(zarr.open_group(str(tmp_path / "cube.zarr"), mode="r")["cube"][...], data)


def test_overwrite_refuses_a_store_of_another_kind(tmp_path, capsys):
    run = make_run(tmp_path / "run.zarr")
    before = _streaks_bytes(run.path)
    write_cube(tmp_path / "cube.zarr", small_cube(2, 3, seed=1), time_bin_ps=TB)
    assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", run.path, "--overwrite", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "it is a streaklab run store (raw capture data)" in err and "remove it yourself" in err
    assert _streaks_bytes(run.path) == before
    # a cube over a run, an export over a cube store, an import over a run: all refused
    assert main(["reconstruct", run.path, "--out", str(tmp_path / "other.zarr")]) == 0
    assert main(["reconstruct", run.path, "--out", run.path + "2"]) == 0
    assert main(["export", str(tmp_path / "other.zarr"), "--out", str(tmp_path / "cube.zarr"), "--overwrite"]) == 2
    assert "it is a streaklab 'cube' store" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "other.zarr"), "--out", str(tmp_path / "c.h5")]) == 0
    assert main(["import", str(tmp_path / "c.h5"), "--out", run.path, "--overwrite"]) == 2
    assert "raw capture data" in capsys.readouterr().err
    assert _streaks_bytes(run.path) == before
    # the same kind is replaced as before
    assert main(["reconstruct", run.path, "--out", str(tmp_path / "other.zarr"), "--overwrite"]) == 0
    assert main(["export", str(tmp_path / "other.zarr"), "--out", str(tmp_path / "c.h5"), "--overwrite"]) == 0


def test_check_output_path_rule(tmp_path):
    (tmp_path / "in.zarr").mkdir()
    (tmp_path / "in.zarr/zarr.json").write_text('{"attributes": {"streaklab_kind": "cube"}}')
    (tmp_path / "foreign.zarr").mkdir()
    (tmp_path / "foreign.zarr/zarr.json").write_text('{"attributes": {}}')
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes/a.txt").write_text("x")
    assert describe_existing(tmp_path / "in.zarr") == "cube"
    assert describe_existing(tmp_path / "foreign.zarr") == "zarr"
    assert describe_existing(tmp_path / "notes") == "directory"
    assert describe_existing(tmp_path / "notes/a.txt") == "file"
    assert describe_existing(tmp_path / "nothing") is None
    with pytest.raises(OutputPathError, match="holds the input"):
        check_output_path(tmp_path / "in.zarr", overwrite=True, inputs=[tmp_path / "in.zarr"], kind="cube")
    with pytest.raises(OutputPathError, match="Zarr store of other software"):
        check_output_path(tmp_path / "foreign.zarr", overwrite=True, kind="cube")
    with pytest.raises(OutputPathError, match="a streaklab 'cube' store"):
        check_output_path(tmp_path / "in.zarr", overwrite=True, kind="decomposition")
    with pytest.raises(FileExistsError, match="already exists"):
        check_output_path(tmp_path / "notes", kind="cube")
    check_output_path(tmp_path / "in.zarr", overwrite=True, kind="cube")
    check_output_path(tmp_path / "notes", overwrite=True, kind="cube")        # no store: replaceable
    (tmp_path / "notes/deep/run.zarr").mkdir(parents=True)                   # ... unless it holds one
    (tmp_path / "notes/deep/run.zarr/zarr.json").write_text('{"attributes": {"streaklab_kind": "run"}}')
    with pytest.raises(OutputPathError, match=r"it holds a streaklab run store \(raw capture data\) at .*deep/run.zarr"):
        check_output_path(tmp_path / "notes", overwrite=True, kind="cube")


def test_resume_refuses_a_store_with_a_link_inside(tmp_path, capsys):
    from decomposition.store.pipeline import decompose_to_store

    write_cube(tmp_path / "cube.zarr", small_cube(2, 3, seed=1), time_bin_ps=TB, chunks=(1, 3))
    res = tmp_path / "res.zarr"
    decompose_to_store(tmp_path / "cube.zarr", res, progress=False)
    g = zarr.open_group(str(res), mode="r+")
    g["done"][...] = False                                  # as if killed before any chunk
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    import shutil

    shutil.rmtree(res / "direct" / "c")
    (res / "direct" / "c").symlink_to(elsewhere, target_is_directory=True)
    assert main(["decompose", str(tmp_path / "cube.zarr"), "--out", str(res), "--resume", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "direct/c is a symbolic link inside the store" in err and "refusing to write through it" in err
    assert list(elsewhere.iterdir()) == []


def test_capture_resume_refuses_a_run_store_with_a_link_inside(tmp_path):
    from acquisition.runstore import RunStoreError, open_run

    run = make_run(tmp_path / "run.zarr")
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "run.zarr" / "streaks" / "c" / "9").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    open_run(run.path)                                     # reading is fine
    with pytest.raises(RunStoreError, match="streaks/c/9 is a symbolic link inside the store"):
        open_run(run.path, mode="r+")


def _tree(path):
    """Every file below ``path`` with its bytes: a store is untouched exactly when this is unchanged."""
    from pathlib import Path

    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(Path(path).rglob("*")) if p.is_file()}


def test_no_command_writes_inside_a_zarr_store(tmp_path, capsys):
    from decomposition.store.pipeline import decompose_to_store
    from streaklab.bench.arguments import output_folder

    run = make_run(tmp_path / "run.zarr")
    write_cube(tmp_path / "cube.zarr", small_cube(2, 3, seed=1), time_bin_ps=TB, chunks=(1, 3))
    decompose_to_store(tmp_path / "cube.zarr", tmp_path / "res.zarr", progress=False)
    (tmp_path / "scan.toml").write_text("[scan]\nangles_deg = [0.0, 1.0]\n[calibration]\ntime_poly_ps = [0.0, 2.0]\n")
    assert main(["export", str(tmp_path / "cube.zarr"), "--out", str(tmp_path / "c.h5")]) == 0
    capsys.readouterr()
    stores = {name: _tree(tmp_path / name) for name in ("run.zarr", "cube.zarr", "res.zarr")}
    run_, cube, res = run.path, str(tmp_path / "cube.zarr"), str(tmp_path / "res.zarr")
    commands = [
        ["capture", "--config", str(tmp_path / "scan.toml"), "--out", f"{run_}/inner.zarr", "--simulate"],
        ["reconstruct", run_, "--out", f"{cube}/new.zarr"],
        ["decompose", cube, "--out", f"{run_}/res.zarr", "--quiet"],
        ["report", res, "--out", f"{cube}/figs"],
        ["report", res, "--out", cube],                          # a folder of figures that is a store
        ["demo", "--out", f"{run_}/demo"],
        ["demo", "--out", run_],
        ["simulate", "--out", f"{res}/sim.zarr", "--shape", "1", "2", "64"],
        ["calibrate-irf", cube, "--out", f"{run_}/irf.zarr"],
        ["calibrate-sweep", run_, "--etalon-ps", "20", "--out", f"{cube}/sweep.zarr"],
        ["calibrate-shading", run_, "--out", f"{cube}/flat.npy"],
        ["export", cube, "--out", f"{res}/c.h5"],
        ["import", str(tmp_path / "c.h5"), "--out", f"{run_}/c.zarr"],
        ["example-config", "--out", f"{cube}/scan.toml"],
        ["live", "--config", str(tmp_path / "scan.toml"), "--simulate", "--png", f"{cube}/live.png", "--no-window"],
    ]
    for argv in commands:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "refusing to write" in err, (argv, err)
        assert "lies inside the Zarr store" in err or "it is a streaklab" in err, (argv, err)
    with pytest.raises(OutputPathError, match=r"lies inside the Zarr store .*cube.zarr, a streaklab 'cube' store"):
        output_folder(f"{cube}/bench")                            # the benchmarks' --out
    for name, files in stores.items():
        assert _tree(tmp_path / name) == files, name
    # a store's own part may still be written where the store means it to be: the cube's response group
    check_output_path(f"{cube}/irf", kind="instrument_response", within=cube)
    with pytest.raises(OutputPathError, match="lies inside the Zarr store"):
        check_output_path(f"{cube}/irf", kind="instrument_response", within=res)


def test_overwrite_never_deletes_files_that_are_not_the_stores(tmp_path, capsys):
    from core.staging import foreign_files

    run = make_run(tmp_path / "run.zarr")
    assert main(["reconstruct", run.path, "--out", str(tmp_path / "cube.zarr")]) == 0
    assert foreign_files(tmp_path / "cube.zarr") == [] and foreign_files(run.path) == []
    (tmp_path / "cube.zarr/frames.png").write_bytes(b"figure")
    (tmp_path / "cube.zarr/cube/notes.txt").write_text("mine")
    assert [p.name for p in foreign_files(tmp_path / "cube.zarr")] == ["notes.txt", "frames.png"]
    before = _tree(tmp_path / "cube.zarr")
    assert main(["reconstruct", run.path, "--out", str(tmp_path / "cube.zarr"), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert "refusing to replace" in err and "not the store's own (cube/notes.txt, frames.png)" in err
    assert _tree(tmp_path / "cube.zarr") == before
    with pytest.raises(OutputPathError, match="frames.png"):            # whatever kind, or none, is asked for
        check_output_path(tmp_path / "cube.zarr", overwrite=True)
    (tmp_path / "cube.zarr/frames.png").unlink()
    (tmp_path / "cube.zarr/cube/notes.txt").unlink()
    assert main(["reconstruct", run.path, "--out", str(tmp_path / "cube.zarr"), "--overwrite"]) == 0
    # resuming writes into the store and deletes nothing: a file of one's own there is no reason to refuse
    write_cube(tmp_path / "c.zarr", small_cube(2, 3, seed=1), time_bin_ps=TB, chunks=(1, 3))
    res = str(tmp_path / "res.zarr")
    assert main(["decompose", str(tmp_path / "c.zarr"), "--out", res, "--quiet"]) == 0
    (tmp_path / "res.zarr/notes.txt").write_text("mine")
    assert main(["decompose", str(tmp_path / "c.zarr"), "--out", res, "--quiet", "--resume"]) == 0
    assert main(["decompose", str(tmp_path / "c.zarr"), "--out", res, "--quiet", "--overwrite"]) == 2
    assert "not the store's own (notes.txt)" in capsys.readouterr().err
    assert (tmp_path / "res.zarr/notes.txt").read_text() == "mine"
