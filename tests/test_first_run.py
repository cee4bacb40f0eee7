"""What a new user meets first: inputs named for what they are, the packaged example config,
and messages that say what to do."""
import numpy as np

from reconstruction.cubestore import write_cube
from streaklab.cli import main


def test_decompose_names_an_hdf5_input_and_how_to_convert_it(tmp_path, capsys):
    from reconstruction.nexus import export_cube

    write_cube(tmp_path / "cube.zarr", np.ones((1, 2, 32), np.float32), time_bin_ps=2.0)
    export_cube(tmp_path / "cube.zarr", tmp_path / "cube.h5")
    assert main(["decompose", str(tmp_path / "cube.h5"), "--out", str(tmp_path / "r.zarr"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "HDF5" in err and "--time-bin-ps" not in err and ".npy" not in err
    assert f"streaklab import {tmp_path / 'cube.h5'} --out cube.zarr" in err
    (tmp_path / "notes.txt").write_text("not data")
    assert main(["decompose", str(tmp_path / "notes.txt"), "--out", str(tmp_path / "r.zarr"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "neither a cube store" in err and "--time-bin-ps" not in err
    assert not (tmp_path / "r.zarr").exists()


def test_a_taken_output_path_is_refused_in_the_command_lines_words(tmp_path, capsys):
    from reconstruction.nexus import export_cube

    write_cube(tmp_path / "cube.zarr", np.ones((1, 2, 32), np.float32), time_bin_ps=2.0)
    export_cube(tmp_path / "cube.zarr", tmp_path / "cube.h5")
    taken = tmp_path / "taken.zarr"
    taken.mkdir()
    (taken / "notes.txt").write_text("keep me")
    for argv in (["simulate", "--shape", "1", "2", "32", "--out", str(taken)],
                 ["export", str(tmp_path / "cube.zarr"), "--out", str(tmp_path / "cube.h5")],
                 ["import", str(tmp_path / "cube.h5"), "--out", str(taken)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.endswith("already exists; pass --overwrite to replace it"), err
        assert "overwrite=True" not in err and len(err.splitlines()) == 1
    assert (taken / "notes.txt").read_text() == "keep me"
