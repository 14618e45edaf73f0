"""The options registry: shared options read the same in every command; -v/-q after the command;
no output (-o or --plot) may replace any input, whatever the option that names it."""

import shutil

import numpy as np
import pytest

from fits_factory import DAY, SHAPE, T0, commands, frame_file, invoke, leaf_commands, listing, snapshot

# -- one meaning per option ---------------------------------------------------------------------

#: option -> (metavar, start of its help) shared by every command that has it
SHARED = {
    "output": ("PATH", "Output FITS file"),
    "overwrite": (None, "Replace the output"),
    "workers": ("N", "Cores to use: "),
    "seed": ("N", "Random seed, written into the output"),
    "plot": ("PNG", "Also draw "),
    "model_spec": (None, "Detector model: "),
}


def _params(command):
    return {p.name: p for p in command.params}


@pytest.mark.parametrize("name", sorted(SHARED))
def test_shared_options_read_the_same_everywhere(name):
    metavar, help_start = SHARED[name]
    # an older spelling kept hidden (apply-persistence --model, now --law) is documented nowhere
    users = [cmd for cmd_name, cmd in leaf_commands() if name in _params(cmd) and not _params(cmd)[name].hidden]
    assert users, name
    for cmd in users:
        p = _params(cmd)[name]
        if metavar is not None:
            assert p.metavar == metavar, (cmd.name, name, p.metavar)
        assert p.help.startswith(help_start), (cmd.name, name, p.help)


def test_every_command_has_output_overwrite_and_verbosity():
    for name, cmd in leaf_commands():
        opts = {o for p in cmd.params for o in getattr(p, "opts", [])}
        assert {"-o", "--output", "--overwrite", "-v", "--verbose", "-q", "--quiet"} <= opts, name


def test_workers_default_to_one_everywhere():
    for name, cmd in leaf_commands():
        p = _params(cmd).get("workers")
        if p is not None:
            assert p.default == 1, name


@pytest.mark.parametrize("command", ["render", "budget", "correlate"])
def test_plot_must_be_a_png_file(tmp_path, command):
    for bad in ("-", str(tmp_path / "figure.pdf")):
        result = invoke(command, "--plot", bad, "-o", tmp_path / "out.fits")
        assert result.exit_code == 2, (command, bad, result.output)
        assert "--plot" in result.stderr
    assert listing(tmp_path) == []


# -- -v and -q after the command -----------------------------------------------------------------

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


def test_verbose_after_the_command(tmp_path, frames):
    out = tmp_path / "out.fits"
    result = invoke("apply-persistence", *frames, "-o", out, "-v")
    assert result.exit_code == 0, result.output
    lines = result.stderr.splitlines()
    assert lines and all(line.startswith("perscli: info: ") for line in lines)


def test_quiet_after_the_command(tmp_path, frames, nan_prev):
    cur, _ = frames
    result = invoke("apply-persistence", cur, nan_prev, "-o", tmp_path / "out.fits", "--quiet")
    assert result.exit_code == 0
    assert result.stderr == ""
    default = invoke("apply-persistence", cur, nan_prev, "-o", tmp_path / "out2.fits")
    assert default.stderr.startswith("perscli: warning: ")


def test_verbosity_before_and_after_add_up(tmp_path, frames):
    missing = tmp_path / "missing.fits"
    result = invoke("-v", "apply-persistence", frames[0], missing, "-o", tmp_path / "out.fits", "-v")
    assert result.exit_code == 1
    assert "Traceback (most recent call last)" in result.stderr     # -v + -v = -vv
    result = invoke("-v", "apply-persistence", frames[0], missing, "-o", tmp_path / "out.fits", "-q")
    assert result.exit_code == 1
    assert result.stderr == f"Error: {missing}: no such file\n"


def test_verbosity_flags_on_every_command_help():
    for name in commands():
        result = invoke(name, "--help")
        assert "-v, --verbose" in result.stdout and "-q, --quiet" in result.stdout, name


# -- no output over an input --------------------------------------------------------------------

def _file(path, content=b"SIMPLE  =                    T" + b" " * 50):
    path.write_bytes(content)
    return str(path)


def refused(tmp_path, args, *, needle="is also an input", inputs=(), code=1):
    """The command fails with one line (exit 1; 2 for a usage error), leaves its inputs unchanged and writes
    nothing."""
    before, files = snapshot(*inputs), listing(tmp_path)
    for extra in ([], ["--overwrite"]):
        result = invoke(*args, *extra)
        assert result.exit_code == code, (args, extra, result.exit_code, result.output)
        lines = result.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("Error: " if code == 1 else "perscli "), result.stderr
        assert needle in lines[0], lines[0]
        assert "Traceback" not in result.stderr
    assert snapshot(*inputs) == before
    assert listing(tmp_path) == files
    return lines[0]


POINTING = ["--ra", "10", "--dec", "-44", "--pa", "30", "--mjd", "61541.97", "--filter", "J129", "--sca", "7",
            "--seed", "1"]


def test_apply_persistence_refuses_output_over_an_input(tmp_path, frames):
    cur, prev = frames
    refused(tmp_path, ["apply-persistence", cur, prev, "-o", prev], inputs=[cur, prev])
    model = _file(tmp_path / "model.yaml", b"A: 0.02\n")
    # a law file as -o: refused by its name first (apply-persistence writes FITS, not YAML); either way untouched
    refused(tmp_path, ["apply-persistence", cur, prev, "--law", model, "-o", model], inputs=[cur, prev, model],
            needle="writes FITS, not YAML", code=2)
    # an input given with CFITSIO's extended syntax is the same file
    refused(tmp_path, ["apply-persistence", cur, f"{prev}[SCI]", "-o", prev], inputs=[cur, prev])


@pytest.mark.parametrize("role", ["truth", "--pointings", "--previous", "--model"])
def test_render_refuses_output_over_an_input(tmp_path, role):
    truth = _file(tmp_path / "truth.fits")
    other = _file(tmp_path / "other.fits")
    args = ["render", truth, *POINTING]
    if role == "truth":
        args += ["-o", truth]
    else:
        args += [role, other, "-o", other]
    refused(tmp_path, args, inputs=[truth, other])


def test_render_refuses_plot_over_an_input_or_the_output(tmp_path):
    truth = _file(tmp_path / "truth.fits")
    picture = _file(tmp_path / "sched.png")
    refused(tmp_path, ["render", truth, *POINTING, "--pointings", picture, "--plot", picture,
                       "-o", tmp_path / "out.fits"], inputs=[truth, picture])
    # -o and --plot naming the same PNG: the -o name is refused first (render writes FITS, not PNG)
    refused(tmp_path, ["render", truth, *POINTING, "--plot", tmp_path / "f.png", "-o", tmp_path / "f.png"],
            needle="writes FITS, not PNG", inputs=[truth], code=2)


@pytest.mark.parametrize("role", ["frame", "--catalog", "--psf"])
def test_measure_refuses_output_over_an_input(tmp_path, role):
    frame = _file(tmp_path / "frame.fits")
    cat = _file(tmp_path / "cat.fits")
    psf = _file(tmp_path / "psf.fits")
    target = {"frame": frame, "--catalog": cat, "--psf": psf}[role]
    refused(tmp_path, ["measure", frame, "--catalog", cat, "--psf", psf, "-o", target], inputs=[frame, cat, psf])


def test_budget_refuses_output_over_an_input(tmp_path):
    xi = _file(tmp_path / "xi.fits")
    refused(tmp_path, ["budget", xi, "-o", xi], inputs=[xi])
    xi_png = _file(tmp_path / "xi.png")
    refused(tmp_path, ["budget", xi_png, "-o", tmp_path / "b.fits", "--plot", xi_png], inputs=[xi_png])
    refused(tmp_path, ["budget", "-o", tmp_path / "b.png", "--plot", tmp_path / "b.png"],
            needle="writes FITS, not PNG", code=2)


@pytest.mark.parametrize("role", ["shapes", "--patch-centers", "--plot"])
def test_correlate_refuses_output_over_an_input(tmp_path, role):
    shapes = _file(tmp_path / "shapes.fits")
    centres = _file(tmp_path / "centres.fits")
    base = ["correlate", shapes, "--frames", "0", "1"]
    if role == "shapes":
        args = base + ["-o", shapes]
    elif role == "--patch-centers":
        args = base + ["--patch-centers", centres, "-o", centres]
    else:
        picture = _file(tmp_path / "shapes.png")
        refused(tmp_path, ["correlate", picture, "--frames", "0", "1", "--plot", picture, "-o",
                           tmp_path / "xi.fits"], inputs=[picture])
        args = base + ["--plot", tmp_path / "xi.png", "-o", tmp_path / "xi.png"]
        refused(tmp_path, args, needle="writes FITS, not PNG", inputs=[shapes], code=2)
        return
    refused(tmp_path, args, inputs=[shapes, centres])


def test_catalog_refuses_output_over_a_gaia_input(tmp_path):
    gaia = _file(tmp_path / "gaia.fits")
    refused(tmp_path, ["catalog", "--ra", "10", "--dec", "-44", "--gaia", gaia, "-o", gaia], inputs=[gaia])


def test_pointings_refuses_output_over_the_schedule(tmp_path):
    sched = _file(tmp_path / "sched.fits")
    refused(tmp_path, ["pointings", "select", "--schedule", sched, "--ra", "10", "--dec", "-44", "--radius", "1",
                       "-o", sched], inputs=[sched])


def test_an_output_through_a_symbolic_link_to_an_input_is_refused(tmp_path, frames):
    cur, prev = frames
    link = tmp_path / "link.fits"
    link.symlink_to(prev)
    refused(tmp_path, ["apply-persistence", cur, prev, "-o", link], inputs=[cur, prev])


def test_sample_model_file_is_never_replaced(tmp_path):
    from conftest import SAMPLE_DATA

    model = tmp_path / "roman_detector.yaml"
    shutil.copy(SAMPLE_DATA / "roman_detector.yaml", model)
    truth = _file(tmp_path / "truth.fits")
    refused(tmp_path, ["render", truth, *POINTING, "--model", model, "-o", model], inputs=[truth, model],
            needle="writes FITS, not YAML", code=2)


# -- coordinates: one definition, range-checked everywhere ---------------------------------------

#: a valid command line of each command that takes coordinates (nothing is read: the options fail first)
COORDINATE_COMMANDS = {
    "catalog": ["catalog", "--ra", "10", "--dec", "-44"],
    "pointings plan": ["pointings", "plan", "--n", "2", "--ra", "10", "--dec", "-44"],
    "pointings select": ["pointings", "select", "--schedule", "sched.fits", "--radius", "1", "--ra", "10", "--dec", "-44"],
    "render": ["render", "truth.fits", "--seed", "1", "--filter", "J129", "--sca", "7", "--ra", "10", "--dec", "-44",
               "--pa", "30", "--mjd", "61541.97"],
}


def _with(args, option, value):
    args = list(args)
    if option in args:
        args[args.index(option) + 1] = value
    else:
        args += [option, value]
    return args


@pytest.mark.parametrize("command", sorted(COORDINATE_COMMANDS))
@pytest.mark.parametrize("option, value", [("--ra", "370"), ("--ra", "-0.5"), ("--ra", "nan"), ("--dec", "91"),
                                           ("--dec", "-90.01"), ("--dec", "nan")])
def test_positions_out_of_range_are_usage_errors(tmp_path, command, option, value):
    result = invoke(*_with(COORDINATE_COMMANDS[command], option, value), "-o", tmp_path / "out.fits")
    assert result.exit_code == 2, (command, option, value, result.output)
    assert f"Invalid value for '{option}'" in result.stderr
    assert result.stderr.startswith(f"perscli {command}: error: ") and len(result.stderr.splitlines()) == 1
    assert listing(tmp_path) == []


@pytest.mark.parametrize("command, option, value, needle", [
    ("render", "--pa", "400", "-360.0<=x<=360.0"),
    ("pointings plan", "--pa", "-361", "-360.0<=x<=360.0"),
    ("render", "--mjd", "2461541.47", "a Julian Date? MJD = JD - 2400000.5 = 61540.97000"),
    ("render", "--mjd", "-1", "0.0<=x<=100000.0"),
    ("pointings plan", "--start", "nan", "is not a number"),
    ("pointings select", "--after", "615419.7", "0.0<=x<=100000.0"),
])
def test_angles_and_dates_out_of_range_are_usage_errors(tmp_path, command, option, value, needle):
    result = invoke(*_with(COORDINATE_COMMANDS[command], option, value), "-o", tmp_path / "out.fits")
    assert result.exit_code == 2, result.output
    assert f"Invalid value for '{option}'" in result.stderr and needle in result.stderr
    assert listing(tmp_path) == []


def test_ra_370_suggests_the_same_direction(tmp_path):
    result = invoke(*_with(COORDINATE_COMMANDS["catalog"], "--ra", "370"), "-o", tmp_path / "out.fits")
    assert "the same direction as 10" in result.stderr


def test_coordinate_options_are_defined_once():
    from perscli.cli import options
    from perscli.scene import DEC_RANGE, MJD_RANGE, PA_RANGE, RA_RANGE

    types = {"ra": options.RA_TYPE, "dec": options.DEC_TYPE, "pa": options.PA_TYPE, "mjd": options.MJD_TYPE,
             "start": options.MJD_TYPE, "after": options.MJD_TYPE}
    seen = set()
    for _, cmd in leaf_commands():
        for p in cmd.params:
            if p.name in types:
                assert p.type is types[p.name], (cmd.name, p.name)
                seen.add((cmd.name, p.name))
    assert {("catalog", "ra"), ("catalog", "dec"), ("pointings", "ra"), ("pointings", "dec"), ("pointings", "pa"),
            ("pointings", "start"), ("pointings", "after"), ("render", "ra"), ("render", "dec"), ("render", "pa"),
            ("render", "mjd")} <= seen
    # the command line and the library agree on the ranges
    for kind, rng in ((options.RA_TYPE, RA_RANGE), (options.DEC_TYPE, DEC_RANGE), (options.PA_TYPE, PA_RANGE),
                      (options.MJD_TYPE, MJD_RANGE)):
        assert (kind.min, kind.max) == rng


def test_plan_reference_date_in_the_help_is_the_librarys():
    from perscli.scene.settings import PLAN_REFERENCE_MJD

    assert str(PLAN_REFERENCE_MJD) in invoke("pointings", "--help").stdout.replace("\n", " ")
