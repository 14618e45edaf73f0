"""The perscli group: --version, --help, verbosity (-v, -q, -vv) and the installed console script."""

import io
import os
import re
import subprocess
import sys
from importlib import metadata

import numpy as np
import pytest
from astropy.io import fits

import perscli

from fits_factory import DAY, SHAPE, T0, commands, frame_file, invoke, listing

SCRIPT = os.path.join(os.path.dirname(sys.executable), "perscli")


@pytest.fixture
def frames(tmp_path):
    prev = frame_file(tmp_path / "prev.fits", np.full(SHAPE, 3e4), start=T0)
    cur = frame_file(tmp_path / "cur.fits", np.full(SHAPE, 50.0), start=T0 + 300.0 / DAY)
    return cur, prev


@pytest.fixture
def nan_prev(tmp_path):
    data = np.full(SHAPE, 3e4)
    data[3, 3] = np.nan
    return frame_file(tmp_path / "nan.fits", data, start=T0)


def test_version():
    result = invoke("--version")
    assert result.exit_code == 0
    assert result.stdout == f"perscli {perscli.__version__}\n"
    assert result.stdout == "perscli 0.1.0\n"


def test_version_matches_the_installed_distribution():
    assert metadata.version("perscli") == perscli.__version__


@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_lists_the_registered_commands(flag):
    result = invoke(flag)
    assert result.exit_code == 0
    text = result.stdout
    assert "Usage:" in text and "--version" in text and "--verbose" in text and "--quiet" in text
    listed = text.split("Commands:", 1)[1]
    # one command per line indented by two spaces; wrapped help lines are indented further
    names = re.findall(r"^  (\S+)", listed, re.M)
    assert names == sorted(commands()) == ["apply-persistence", "budget", "catalog", "completion", "correlate",
                                             "diagnose", "man", "measure", "pointings", "render", "study"]


def test_no_command_shows_usage():
    result = invoke()
    assert result.exit_code in (0, 2)
    assert "apply-persistence" in result.output


def test_unknown_command_is_a_usage_error():
    result = invoke("apply-persistance")
    assert result.exit_code == 2
    assert result.stderr == ("perscli: error: No such command 'apply-persistance'. Did you mean "
                             "'apply-persistence'? (see 'perscli -h')\n")


def test_command_help_documents_conventions():
    result = invoke("apply-persistence", "--help")
    assert result.exit_code == 0
    for word in ("CURRENT", "PREVIOUS...", "--output", "--mode", "--units", "--gain", "--exptime", "--gap",
                 "--overwrite", "EXPSTART/EXPEND", "READTIMES"):
        assert word in result.stdout, word


# -- verbosity ---------------------------------------------------------------------------------

def test_default_run_is_silent(tmp_path, frames):
    result = invoke("apply-persistence", *frames, "-o", tmp_path / "out.fits")
    assert result.exit_code == 0
    assert result.stderr == "" and result.stdout == ""


@pytest.mark.parametrize("flag", ["-v", "--verbose"])
def test_verbose_shows_info_lines(tmp_path, frames, flag):
    out = tmp_path / "out.fits"
    result = invoke(flag, "apply-persistence", *frames, "-o", out)
    assert result.exit_code == 0
    lines = result.stderr.splitlines()
    assert lines and all(line.startswith("perscli: info: ") for line in lines)
    assert any(str(out) in line and "1 earlier exposure" in line for line in lines)
    assert result.stdout == ""


def test_warnings_shown_by_default(tmp_path, frames, nan_prev):
    cur, _ = frames
    result = invoke("apply-persistence", cur, nan_prev, "-o", tmp_path / "out.fits")
    assert result.exit_code == 0
    assert result.stderr.startswith("perscli: warning: ")
    assert "non-finite" in result.stderr


@pytest.mark.parametrize("flag", ["-q", "--quiet"])
def test_quiet_suppresses_warnings(tmp_path, frames, nan_prev, flag):
    cur, _ = frames
    out = tmp_path / "out.fits"
    result = invoke(flag, "apply-persistence", cur, nan_prev, "-o", out)
    assert result.exit_code == 0
    assert result.stderr == ""
    assert out.exists()


def test_quiet_still_reports_errors(tmp_path, frames):
    cur, _ = frames
    missing = tmp_path / "missing.fits"
    result = invoke("-q", "apply-persistence", cur, missing, "-o", tmp_path / "out.fits")
    assert result.exit_code == 1
    assert result.stderr == f"Error: {missing}: no such file\n"


def test_verbose_and_quiet_cancel(tmp_path, frames, nan_prev):
    cur, _ = frames
    result = invoke("-v", "-q", "apply-persistence", cur, nan_prev, "-o", tmp_path / "out.fits")
    assert result.exit_code == 0
    assert "warning" in result.stderr and "info" not in result.stderr


def test_error_without_vv_has_no_traceback(tmp_path, frames):
    cur, _ = frames
    result = invoke("-v", "apply-persistence", cur, tmp_path / "missing.fits", "-o", tmp_path / "out.fits")
    assert result.exit_code == 1
    assert "Traceback" not in result.stderr
    assert len(result.stderr.splitlines()) == 1


def test_vv_on_an_error_shows_a_traceback(tmp_path, frames):
    cur, _ = frames
    missing = tmp_path / "missing.fits"
    result = invoke("-vv", "apply-persistence", cur, missing, "-o", tmp_path / "out.fits")
    assert result.exit_code == 1
    assert "Traceback (most recent call last)" in result.stderr
    assert "perscli.PerscliError" in result.stderr
    assert "open_frame" in result.stderr
    # the one-line error is still the last line
    assert result.stderr.splitlines()[-1] == f"Error: {missing}: no such file"
    assert not (tmp_path / "out.fits").exists()


def test_vv_includes_info_lines(tmp_path, frames):
    result = invoke("-vv", "apply-persistence", *frames, "-o", tmp_path / "out.fits")
    assert result.exit_code == 0
    assert "perscli: info: " in result.stderr


# -- standard input and output -----------------------------------------------------------------

def test_pipe_from_stdin_to_stdout(tmp_path, frames):
    cur, prev = frames
    before = listing(tmp_path)
    with open(cur, "rb") as fh:
        raw = fh.read()
    result = invoke("apply-persistence", "-", prev, "-o", "-", input=raw)
    assert result.exit_code == 0, result.stderr
    assert result.stderr == ""
    assert listing(tmp_path) == before
    with fits.open(io.BytesIO(result.stdout_bytes), checksum=True) as hdul:
        assert hdul[0].header["PSCUR"] == "stdin"
        assert hdul[0].header["PSP01"] == "prev.fits"
        assert np.all(hdul[1].data > 50.0)


def test_two_inputs_from_stdin_are_refused(tmp_path):
    result = invoke("apply-persistence", "-", "-", "-o", tmp_path / "out.fits", input=b"")
    assert result.exit_code == 1
    assert result.stderr == "Error: only one input can be read from standard input ('-')\n"


# -- the installed console script, in a real process -------------------------------------------

def _script(*args, **kw):
    if not os.path.exists(SCRIPT):
        pytest.skip("the perscli console script is not installed next to this Python")
    return subprocess.run([SCRIPT, *map(str, args)], capture_output=True, timeout=120, **kw)


def test_console_script_version():
    proc = _script("--version")
    assert proc.returncode == 0
    assert proc.stdout.decode() == f"perscli {perscli.__version__}\n"


def test_console_script_data_error_is_one_line_and_exit_1(tmp_path, frames):
    cur, _ = frames
    missing = tmp_path / "missing.fits"
    proc = _script("apply-persistence", cur, missing, "-o", tmp_path / "out.fits")
    assert proc.returncode == 1
    assert proc.stdout == b""
    assert proc.stderr.decode() == f"Error: {missing}: no such file\n"


def test_console_script_usage_error_exit_2(tmp_path, frames):
    proc = _script("apply-persistence", *frames)
    assert proc.returncode == 2
    assert proc.stdout == b""
    assert proc.stderr.decode() == ("perscli apply-persistence: error: Missing option '-o' / '--output' "
                                    "(see 'perscli apply-persistence -h')\n")


def test_progress_bar_on_a_terminal_and_no_lines_for_small_work_otherwise():
    import io

    from perscli.cli.helpers import progress_reporter

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    term = Terminal()
    progress = progress_reporter("rows", stream=term)
    for done in range(1, 5):
        progress(done, 4)
    assert "rows" in term.getvalue() and "100%" in term.getvalue()
    # not a terminal: a line per tenth of work of at least `least` steps (tests/test_progress.py), none for less
    log = io.StringIO()
    small = progress_reporter("rows", stream=log, least=5)
    for done in range(1, 5):
        small(done, 4)
    assert log.getvalue() == ""
