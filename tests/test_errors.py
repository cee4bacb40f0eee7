"""One error base for the data layer: every library error is a ``StreaklabError`` (keeping its
built-in base), and the command line prints any of them as ``streaklab CMD: error: ...``, status 2."""
import pytest

from acquisition.config import ConfigError
from acquisition.runstore import RunStoreError
from acquisition.session import CaptureError, CaptureFailed
from core.errors import OutputExistsError, StreaklabError
from core.staging import check_output_path
from decomposition.store.pipeline import PipelineError
from decomposition.store.resultstore import ResultStoreError
from drivers.errors import DriverError
from reconstruction.build import ReconstructionError
from reconstruction.calibrate import CalibrationError
from reconstruction.cubestore import CubeStoreError
from reconstruction.nexus import NexusError
from streaklab import cli


@pytest.mark.parametrize("cls, builtin", [
    (ConfigError, ValueError), (RunStoreError, ValueError), (CaptureError, RuntimeError),
    (CaptureFailed, RuntimeError), (CubeStoreError, ValueError), (CalibrationError, ValueError),
    (NexusError, ValueError), (ReconstructionError, ValueError), (ResultStoreError, ValueError),
    (PipelineError, ValueError), (OutputExistsError, FileExistsError),
])
def test_library_errors_share_one_base_and_keep_their_builtin_one(cls, builtin):
    assert issubclass(cls, StreaklabError)
    assert issubclass(cls, builtin)


def test_driver_errors_keep_their_own_base():
    assert not issubclass(DriverError, StreaklabError)


def test_an_occupied_output_path_is_a_library_error(tmp_path):
    (tmp_path / "taken").write_text("x")
    with pytest.raises(OutputExistsError, match="already exists"):
        check_output_path(tmp_path / "taken")
    check_output_path(tmp_path / "taken", overwrite=True)
    check_output_path(tmp_path / "free")


def test_the_command_line_prints_any_library_error(monkeypatch, capsys):
    import streaklab.commands.report as report_cmd

    def fail(args):
        raise ResultStoreError("res.zarr: not a result store")

    monkeypatch.setattr(report_cmd, "run", fail)
    assert cli.main(["report", "res.zarr", "--out", "figs"]) == 2
    assert capsys.readouterr().err == "streaklab report: error: res.zarr: not a result store\n"


def test_a_pipeline_error_reaches_the_user_without_a_traceback(tmp_path, capsys):
    assert cli.main(["decompose", str(tmp_path / "missing.zarr"), "--out", str(tmp_path / "r.zarr")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("streaklab decompose: error: not a usable cube:")
    assert "Traceback" not in err
    assert not (tmp_path / "r.zarr").exists()
