"""Progress on stderr for long work: a bar at a terminal, a line per step (or per tenth of the work) elsewhere,
nothing with -q, nothing for small work in a log (perscli.progress, perscli.cli.progress and the commands that
report through them)."""

import io

import pytest

from perscli.cli.progress import bar, reporter
from perscli.progress import lines

from fits_factory import invoke
from test_measure_cli import scene  # noqa: F401  (a fixture: a truth catalogue and frames on a cutout)


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_lines_say_the_start_each_tenth_and_the_end():
    out = io.StringIO()
    progress = lines("render: objects", out, every=0.1)
    for k in range(1, 1001):
        progress(k, 1000, f"object {k}")
    said = out.getvalue().splitlines()
    assert len(said) == 11 and said[0].startswith("render: objects: [1/1000] object 1; ")
    assert said[1].startswith("render: objects: [100/1000] object 100; ")
    assert said[-1].startswith("render: objects: [1000/1000] object 1000; ") and said[-1].endswith("s elapsed")


def test_small_work_tells_a_log_nothing_and_quiet_says_nothing():
    out = io.StringIO()
    progress = lines("render: objects", out, every=0.1, least=1000)
    for k in range(1, 51):
        progress(k, 50)
    quiet = lines("study", out, quiet=True)
    quiet(1, 2, "x")
    assert out.getvalue() == ""
    assert reporter("objects", io.StringIO(), quiet=True) is None and bar("objects", Terminal(), quiet=True) is None


def test_a_terminal_gets_a_bar_and_a_log_gets_lines():
    log = io.StringIO()
    reporter("objects", log, command="render")(1, 1, "star")
    assert log.getvalue().startswith("render: objects: [1/1] star; ")
    term = Terminal()
    progress = reporter("objects", term, command="render")
    progress(1, 2)
    progress(2, 2)
    assert "objects" in term.getvalue() and "[1/1]" not in term.getvalue() and "\n" in term.getvalue()


def test_the_study_plan_says_each_sca_even_without_a_terminal(tmp_path):
    result = invoke("study", "--preset", "small", "--set", "scas=[7,8]", "-o", tmp_path / "s", "--dry-run")
    assert result.exit_code == 0, result.stderr
    said = result.stderr.splitlines()
    assert said[0].startswith("study: planning: [0/2] SCA 7: its footprints in 16956 exposures; ")
    assert said[1].startswith("study: planning: [1/2] SCA 8: ") and said[2].startswith("study: planning: [2/2] ")
    assert result.stdout.startswith("study small: ")


def test_the_study_plan_is_quiet_with_q(tmp_path):
    quiet = invoke("-q", "study", "--preset", "small", "-o", tmp_path / "s", "--dry-run")
    assert quiet.exit_code == 0 and quiet.stderr == "" and quiet.stdout.startswith("study small: ")


@pytest.mark.parametrize("module, args", [
    ("render", ["render", "T", "--ra", 10, "--dec", -44, "--pa", 30, "--mjd", 61541.97, "--filter", "J129", "--sca",
                7, "--bounds", 1, 64, 1, 64, "--seed", 1]),
    ("measure", ["measure", "F", "--catalog", "T", "--stamp", 16, "--min-snr", 0]),
    ("apply_persistence", ["apply-persistence", "S4", "S3"]),
])
def test_long_work_of_a_command_reports_in_lines_without_a_terminal(scene, tmp_path, monkeypatch, module, args):
    """The commands' progress reaches a log: here their threshold (a full frame's work) lowered to one step."""
    import importlib

    from conftest import SAMPLE_DATA

    command = importlib.import_module(f"perscli.cli.{module}")
    _, truth, frame, _ = scene
    files = {"S4": str(SAMPLE_DATA / "exp4.fits"), "S3": str(SAMPLE_DATA / "exp3.fits"), "T": str(truth),
             "F": str(frame)}
    argv = [files.get(a, a) for a in args]
    quiet = invoke("-q", *argv, "-o", tmp_path / "q.fits")
    assert quiet.exit_code == 0 and quiet.stderr == "", quiet.stderr
    monkeypatch.setattr(command, "PROGRESS_LEAST", 1)
    result = invoke(*argv, "-o", tmp_path / "out.fits")
    assert result.exit_code == 0, result.stderr
    said = [line for line in result.stderr.splitlines() if line.startswith(f"{args[0]}: ")]
    assert said and said[-1].split(": [", 1)[1].split("]")[0].split("/")[0] == \
        said[-1].split(": [", 1)[1].split("]")[0].split("/")[1], result.stderr
    monkeypatch.setattr(command, "PROGRESS_LEAST", 10 ** 9)
    small = invoke(*argv, "-o", tmp_path / "small.fits")
    assert not [line for line in small.stderr.splitlines() if line.startswith(f"{args[0]}: ")], small.stderr
