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
