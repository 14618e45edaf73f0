"""Fuzz suite for the *values* in perscli's inputs, where tests/test_fuzz.py corrupts their *bytes*.

Valid FITS files, correctly signed, whose values no object or exposure can have, and special files
where a file is expected (issue 18, items 2, 3, 5, 8 and 9):

- catalogue values, for render and measure: hlr = 0, < 0 or infinite, |e| >= 1, RA 1e6 off, Dec = 100,
  repeated ids, TSCALn = 0 (every value of the column equal);
- a pointings schedule or table with an exposure time <= 0;
- ``correlate --patch-centers`` naming a FIFO without a writer, /dev/null, a folder, /dev/zero, an empty
  file, a broken link;
- correlate on shapes with |g| >= 1 or |De| >= 2 and positions with |Dec| > 90;
- measure's --no-checksum and --columns, the count lines of pointings and catalog, study's
  --no-checksum, the joint table's flux unit and three figures (the legends of the budget and
  of xi, bin_theta's scale).

A refused case ends with exit status 1, exactly one line on stderr naming the file and the fault, no
traceback, nothing in the output folder and every input unchanged; a hang is caught by the run's
deadline (tests/fuzz_corpus.py's ForkServer kills the run), never by waiting.  The inputs are the small
seeds of tests/fuzz_corpus.py (a 32 x 32 frame with two galaxies, a four-row truth catalogue, a
24-object SHAPES table): the whole file runs in well under a minute.  Every refused case has a valid
twin that must be accepted, so that a check which refuses too much fails here too.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

import fuzz_corpus as fc

#: seconds after which a run is killed and reported as a hang: a deadline for a hung run, not a measure of speed
#: (a refused run takes ~0.1 s, a measure ~2 s), so generous that a loaded machine never reaches it
TIMEOUT = 300.0
MEMORY = 3 * fc.GiB       # RLIMIT_AS of every run: /dev/zero read into memory ends here, not in swap

CORRELATE_ARGS = ["--frames", "0", "1", "--npatch", "2", "--nbins", "2", "--nboot", "2", "--min-sep", "1",
                  "--max-sep", "20", "--seed", "3"]
#: the same without --npatch, which does not go with --patch-centers
PATCH_ARGS = [a for k, a in enumerate(CORRELATE_ARGS) if k not in (3, 4)]
MEASURE_ARGS = ["--stamp", "16"]
#: rows of the truth seed: 0 and 1 lie on the frame seed (measure), 2 (a galaxy) and 3 (a star, hlr 0)
#: in the render cutout of fc.RENDER_ARGS
ROW = {"measure": 0, "render": 2}


# =================================================================================================
# Inputs and runs
# =================================================================================================

@pytest.fixture(scope="module")
def server():
    srv = fc.ForkServer(memory=MEMORY).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    """The valid seeds as files (truth, frame, psf, shapes), never modified."""
    folder = tmp_path_factory.mktemp("seeds")
    out = {}
    for name in ("truth", "frame", "psf", "shapes"):
        path = folder / f"{name}.fits"
        path.write_bytes(fc.seeds()[name])
        out[name] = str(path)
    return out


def with_values(seed: str, path: Path, *, hdu: int = 1, **changes) -> str:
    """A copy of the FITS file ``seed`` with table values changed ({column: (row, value)}), re-signed."""
    with fits.open(seed) as hdul:
        copy = fits.HDUList([h.copy() for h in hdul])
    data = copy[hdu].data
    for column, (row, value) in changes.items():
        data[column][row] = value
    copy.writeto(path, checksum=True)
    return str(path)


def _digest(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def snapshot(paths) -> dict:
    """sha256 of every regular file among ``paths`` (FIFOs and devices are never read)."""
    return {str(p): _digest(p) for p in paths if os.path.isfile(p) and not os.path.islink(p)}


def perscli(server, args, *, cwd, inputs=(), timeout=TIMEOUT, env=None) -> dict:
    """Run ``perscli ARGS`` as a process would (a fork of the test server); the run, with the inputs'
    digests before and after."""
    before = snapshot(inputs)
    run = server.run([str(a) for a in args], cwd=str(cwd), timeout=timeout, env=env)
    run["changed"] = [p for p, d in before.items() if snapshot([p]).get(p) != d]
    run["args"] = [str(a) for a in args]
    return run


def _where(run) -> str:
    return f"$ perscli {' '.join(run['args'])}\n  exit {run['code']}; stderr:\n{run['stderr']}"


def refused(server, folder: Path, args, *needles, inputs=(), timeout=TIMEOUT, env=None) -> str:
    """Run a command that must be refused: exit 1, one line on stderr holding every needle, no traceback,
    the output folder ``folder/out`` left empty and the inputs unchanged.  Returns the line."""
    out = folder / "out"
    out.mkdir(parents=True, exist_ok=True)
    run = perscli(server, [*args, "-o", out / "out.fits"], cwd=folder, inputs=inputs, timeout=timeout, env=env)
    assert not run["timed_out"], f"[hang] {_where(run)}"
    assert "Traceback" not in run["stderr"], f"[traceback] {_where(run)}"
    assert run["code"] == 1, f"[exit {run['code']}] {_where(run)}"
    lines = run["stderr"].splitlines()
    assert len(lines) == 1, f"[message] not one line: {_where(run)}"
    for needle in needles:
        assert needle in lines[0], f"[message] {needle!r} not named: {_where(run)}"
    assert not os.listdir(out), f"[partial output] {os.listdir(out)}: {_where(run)}"
    assert not run["changed"], f"[input modified] {run['changed']}"
    return lines[0]


def accepted(server, folder: Path, args, *, inputs=(), timeout=TIMEOUT, env=None, output=True) -> dict:
    """Run a command that must succeed (exit 0, no traceback, inputs unchanged); the run, with ``out``."""
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / "out.fits"
    run = perscli(server, [*args, "-o", out] if output else args, cwd=folder, inputs=inputs, timeout=timeout,
                  env=env)
    assert not run["timed_out"], f"[hang] {_where(run)}"
    assert "Traceback" not in run["stderr"], f"[traceback] {_where(run)}"
    assert run["code"] == 0, f"[refused] {_where(run)}"
    assert not run["changed"], f"[input modified] {run['changed']}"
    run["out"] = out
    return run


def command(name: str, catalogue: str, seeds: dict) -> list:
    """The render or measure command line reading the truth catalogue ``catalogue``."""
    if name == "render":
        return ["render", catalogue, *fc.RENDER_ARGS]
    return ["measure", seeds["frame"], "--catalog", catalogue, "--psf", seeds["psf"], *MEASURE_ARGS]


# =================================================================================================
# Item 3: catalogue values, one check for render and measure
# =================================================================================================

def _truth_row(seeds, row):
    with fits.open(seeds["truth"]) as hdul:
        return {name: hdul[1].data[name][row] for name in ("id", "ra", "dec")}


#: name -> (changes of the row as a function of its values, words the error line must hold)
CATALOGUE_CASES = {
    "hlr-zero": (lambda r: {"hlr": 0.0}, ["hlr", "half-light radius"]),
    "hlr-negative": (lambda r: {"hlr": -0.3}, ["hlr", "-0.3"]),
    "hlr-infinite": (lambda r: {"hlr": np.inf}, ["hlr"]),
    "e-above-1": (lambda r: {"e1": 0.9, "e2": 0.8}, ["|e|", "e1 = 0.9"]),
    "e-exactly-1": (lambda r: {"e1": 1.0, "e2": 0.0}, ["|e|"]),
    "e-huge": (lambda r: {"e1": 1e300, "e2": 1e300}, ["|e|"]),
    "ra-plus-1e6": (lambda r: {"ra": r["ra"] + 1e6}, ["RA outside [0, 360]"]),
    "ra-negative": (lambda r: {"ra": -r["ra"]}, ["RA outside [0, 360]"]),
    "dec-100": (lambda r: {"dec": 100.0}, ["Dec outside [-90, 90]", "dec=100"]),
    "duplicate-id": (lambda r: {"id": r["id"] - 1 if r["id"] > 1 else r["id"] + 1}, ["appears more than once"]),
}


@pytest.mark.parametrize("name", ["render", "measure"])
def test_a_valid_catalogue_is_accepted(server, seeds, tmp_path, name):
    """The twin of every refused case below: the seed itself (a star with hlr = 0 among them) passes."""
    run = accepted(server, tmp_path, command(name, seeds["truth"], seeds), inputs=seeds.values())
    with fits.open(run["out"], checksum=True) as hdul:
        assert hdul[0].header["NOBJ" if name == "render" else "NFIT01"] >= 1


@pytest.mark.parametrize("case", sorted(CATALOGUE_CASES))
@pytest.mark.parametrize("name", ["render", "measure"])
def test_catalogue_values_are_refused_in_one_line(server, seeds, tmp_path, name, case):
    """Before: render crashed (ZeroDivisionError, GalSim's range error), measure gave WCS tracebacks or
    exit 0 with a silently wrong or uncorrelatable output (repeated ids)."""
    changes, needles = CATALOGUE_CASES[case]
    row = ROW[name]
    values = {column: (row, value) for column, value in changes(_truth_row(seeds, row)).items()}
    if case == "duplicate-id":
        # the other row of the same pair takes this row's id
        other = row + 1
        values = {"id": (other, _truth_row(seeds, row)["id"])}
    bad = with_values(seeds["truth"], tmp_path / "bad.fits", **values)
    refused(server, tmp_path, command(name, bad, seeds), "bad.fits", *needles, inputs=[bad, *seeds.values()])


@pytest.mark.parametrize("name", ["render", "measure"])
@pytest.mark.parametrize("key", ["TSCAL2", "TSCAL3"])
def test_a_column_scaled_by_zero_is_refused(server, seeds, tmp_path, name, key):
    """TSCALn = 0 makes every value TZEROn (RA or Dec all 0): before, measure ran on those positions."""
    bad = tmp_path / "tscal.fits"
    bad.write_bytes(fc.edit(fc.seeds()["truth"], 1, insert=[fc.card(key, "0")]))
    refused(server, tmp_path, command(name, str(bad), seeds), "tscal.fits", key, inputs=[bad, *seeds.values()])


def test_measure_shapes_of_a_catalogue_with_repeated_ids_would_be_refused_by_correlate(seeds, tmp_path):
    """Why measure must refuse repeated ids: correlate refuses the SHAPES table they make."""
    from perscli import PerscliError
    from perscli.measure.selection import read_positions
    from perscli.stats.shape_changes import load_shape_changes

    shapes = with_values(seeds["shapes"], tmp_path / "dup_shapes.fits", id=(1, 1))
    with pytest.raises(PerscliError, match="appears more than once"):
        load_shape_changes([shapes], frames=(0, 1))
    truth = with_values(seeds["truth"], tmp_path / "dup_truth.fits", id=(1, 1))
    with pytest.raises(PerscliError, match="appears more than once"):
        read_positions(truth)


# =================================================================================================
# Item 3: pointings with an exposure time <= 0
# =================================================================================================

def schedule_file(path: Path, exptimes) -> str:
    """A schedule of exposures at (10, -44), one a day, with these exposure times."""
    n = len(exptimes)
    cols = [fits.Column("date", "D", array=61541.97 + np.arange(n)),
            fits.Column("exptime", "D", array=np.asarray(exptimes, dtype=float)),
            fits.Column("ra", "D", array=np.full(n, 10.0)), fits.Column("dec", "D", array=np.full(n, -44.0)),
            fits.Column("pa", "D", array=np.full(n, 30.0)), fits.Column("filter", "4A", array=["J129"] * n)]
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols)]).writeto(path, checksum=True)
    return str(path)


SELECT = ["--ra", "10", "--dec", "-44", "--radius", "1"]


def test_a_schedule_with_positive_times_is_accepted(server, tmp_path):
    good = schedule_file(tmp_path / "sched.fits", [139.8, 139.8, np.nan])   # a row without a time is skipped
    run = accepted(server, tmp_path / "run", ["pointings", "select", "--schedule", good, *SELECT], inputs=[good])
    with fits.open(run["out"]) as hdul:
        assert list(hdul["POINTINGS"].data["exptime"]) == [139.8, 139.8]


@pytest.mark.parametrize("exptime", [-139.8, 0.0, -np.inf])
def test_a_schedule_with_an_exposure_time_of_zero_or_less_is_refused(server, tmp_path, exptime):
    bad = schedule_file(tmp_path / "sched.fits", [139.8, exptime])
    refused(server, tmp_path, ["pointings", "select", "--schedule", bad, *SELECT], "sched.fits", "exptime",
            "row 1", inputs=[bad])


def test_a_pointings_table_with_a_negative_exposure_time_is_refused(server, tmp_path):
    """A pointings table (what render and catalog --pointings read) needs a time > 0 in every row."""
    from perscli.scene.pointings import write_pointings
    from perscli.scene.schedule import Pointing

    rows = [Pointing(expid=k, mjd=61541.97 + k, exptime=t, ra=10.0, dec=-44.0, pa=30.0, filter="J129", sca=7)
            for k, t in enumerate((139.8, -139.8))]
    bad = tmp_path / "plan.fits"
    write_pointings(rows, str(bad), step="test")
    args = ["catalog", "--pointings", bad, "--bounds", "1", "16", "1", "16"]
    refused(server, tmp_path, args, "plan.fits", "exptime", "-139.8", inputs=[bad])
    write_pointings([rows[0]], str(tmp_path / "good.fits"), step="test")
    accepted(server, tmp_path / "run", [*args[:2], tmp_path / "good.fits", *args[3:]], inputs=[tmp_path / "good.fits"])


# =================================================================================================
# Item 2: --patch-centers goes through the input checks
# =================================================================================================

def _special(kind: str, folder: Path) -> str:
    """A name of each kind of file that is no patch-centre file."""
    path = folder / f"centres-{kind}"
    if kind == "fifo":
        os.mkfifo(path)             # and no writer: reading it would block for ever
    elif kind == "dir":
        path.mkdir()
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "broken-link":
        os.symlink(folder / "nowhere", path)
    elif kind == "missing":
        pass
    else:
        return {"devnull": os.devnull, "devzero": "/dev/zero"}[kind]
    return str(path)


@pytest.mark.parametrize("kind, needle", [("fifo", "named pipe"), ("devnull", "not a regular file"),
                                          ("devzero", "not a regular file"), ("dir", "directory"),
                                          ("empty", "empty"), ("broken-link", "broken symbolic link"),
                                          ("missing", "no such file")])
def test_patch_centers_that_are_no_file_are_refused_up_front(server, seeds, tmp_path, kind, needle):
    """Before: a FIFO without a writer hung, /dev/null and a folder gave tracebacks, /dev/zero was read until
    the memory ran out.  Now every one is refused before a table is read; the FIFO without waiting for a
    writer (PERSCLI_FIFO_TIMEOUT, the wait of FITS inputs, is set far beyond the run's deadline, so a reader
    that waited would be killed there and reported as a hang)."""
    name = _special(kind, tmp_path)
    refused(server, tmp_path, ["correlate", seeds["shapes"], *PATCH_ARGS,
                               "--patch-centers", name], name, needle, "--patch-centers",
            inputs=seeds.values(), env={"PERSCLI_FIFO_TIMEOUT": "1000"})


def test_a_text_file_of_patch_centres_is_accepted(server, seeds, tmp_path):
    """The twin of the refusals: TreeCorr's text format (x y z unit vectors) and ra/dec in degrees still work."""
    from perscli.scene import unit_vector

    sky = ((9.9, -44.1), (10.1, -43.9))
    vectors = tmp_path / "vectors.dat"
    np.savetxt(vectors, np.array([unit_vector(ra, dec) for ra, dec in sky]), header="x y z", comments="")
    radec = tmp_path / "radec.dat"
    radec.write_text("ra dec\n" + "".join(f"{ra} {dec}\n" for ra, dec in sky))
    for centres in (vectors, radec):
        run = accepted(server, tmp_path / centres.stem, ["correlate", seeds["shapes"], *PATCH_ARGS,
                                                         "--patch-centers", centres],
                       inputs=[centres, *seeds.values()])
        with fits.open(run["out"]) as hdul:
            assert len(hdul["PATCHES"].data) == 2


@pytest.mark.parametrize("case, needle", [("dec-100", "Dec outside [-90, 90]"), ("ra-1e6", "RA outside [0, 360]"),
                                           ("huge-text", "over 16 MiB of text")])
def test_patch_centre_files_with_impossible_contents_are_refused(server, seeds, tmp_path, case, needle):
    """Regular files that are no patch centres: ra/dec off the sky (folded into another centre before), and a
    text file too large to be one (read whole into memory before: a disk image given by mistake)."""
    centres = tmp_path / "centres.dat"
    if case == "huge-text":
        with open(centres, "wb") as fh:         # sparse: 16 MiB + 1 of zero bytes, nothing written to disk
            fh.truncate((16 << 20) + 1)
    else:
        ra, dec = (1e6, -44.0) if case == "ra-1e6" else (10.0, 100.0)
        centres.write_text(f"ra dec\n9.9 -44.1\n{ra} {dec}\n")
    refused(server, tmp_path, ["correlate", seeds["shapes"], *PATCH_ARGS, "--patch-centers", centres],
            "centres.dat", needle, inputs=[centres, *seeds.values()])


# =================================================================================================
# Item 5: correlate on |g| >= 1, |De| >= 2, |Dec| > 90
# =================================================================================================

#: rows of the shapes seed: 0..23 are frame 0 (A), 24..47 frame 1 (B), the same objects
SHAPES_CASES = {
    "g-3-in-A": ({"g1": (0, 3.0)}, ["1 unflagged row(s) with |g| = |(g1, g2)| >= 1", "frame 0", "id 1"]),
    "g-1e300-in-B": ({"g1": (24, 1e300)}, ["|g| = |(g1, g2)| >= 1", "frame 1"]),
    "g-infinite": ({"g2": (30, np.inf)}, ["|g| = |(g1, g2)| >= 1"]),
    "g-just-above-1": ({"g1": (5, 0.8), "g2": (5, 0.6000001)}, ["|g| = |(g1, g2)| >= 1"]),
    "g-exactly-1": ({"g1": (6, 1.0), "g2": (6, 0.0)}, ["|g| = |(g1, g2)| >= 1"]),
    "g-in-two-rows": ({"g1": (1, -2.0), "g2": (2, 5.0)}, ["2 unflagged row(s)", "first: id 2"]),
    "dec-95-in-B": ({"dec": (24, 95.0)}, ["Dec outside [-90, 90]", "dec=95"]),
    "dec-minus-100-in-A": ({"dec": (0, -100.0)}, ["Dec outside [-90, 90]"]),
    "ra-1e6": ({"ra": (26, 1e6)}, ["RA outside [0, 360]"]),
}


def _finite_products(path) -> None:
    """XI, COV and STATS of a correlate output hold no NaN or infinity."""
    with fits.open(path, checksum=True) as hdul:
        for name in ("XI", "STATS"):
            data = hdul[name].data
            for column in data.columns.names:
                if data[column].dtype.kind == "f":
                    assert np.all(np.isfinite(data[column])), (name, column)
        assert np.all(np.isfinite(hdul["COV"].data))


def test_valid_shapes_and_flagged_wild_ones_are_accepted(server, seeds, tmp_path):
    """|g| > 1 in a row measure flagged (flag 32: |g| reached 1) is left out like any flagged row."""
    flagged = with_values(seeds["shapes"], tmp_path / "flagged.fits", g1=(3, 1.5), flags=(3, 32))
    for k, shapes in enumerate((seeds["shapes"], flagged)):
        run = accepted(server, tmp_path / f"run{k}", ["correlate", shapes, *CORRELATE_ARGS],
                       inputs=[shapes])
        _finite_products(run["out"])
        with fits.open(run["out"]) as hdul:
            assert hdul["STATS"].data["n"][0] == fc.NSHAPES - k


@pytest.mark.parametrize("case", sorted(SHAPES_CASES))
def test_shapes_beyond_one_and_positions_off_the_sky_are_refused(server, seeds, tmp_path, case):
    """Before: exit 0 with NaN and inf in XI, COV and STATS (|g| = 1e300), or positions folded over the pole."""
    changes, needles = SHAPES_CASES[case]
    bad = with_values(seeds["shapes"], tmp_path / "bad.fits", **changes)
    refused(server, tmp_path, ["correlate", bad, *CORRELATE_ARGS], "bad.fits", *needles, inputs=[bad])


def test_de_columns_beyond_two_are_refused(server, seeds, tmp_path):
    """De columns (--de1/--de2) are differences of two shapes: |De| <= 2."""
    bad = with_values(seeds["shapes"], tmp_path / "bad.fits", g1=(7, 2.5))
    args = ["correlate", bad, "--de1", "g1", "--de2", "g2", *CORRELATE_ARGS[3:]]
    refused(server, tmp_path, args, "bad.fits", "|De| = |(g1, g2)| >= 2", inputs=[bad])
    good = with_values(seeds["shapes"], tmp_path / "good.fits", g1=(7, 1.9))     # |De| up to 2 is a shape change
    accepted(server, tmp_path / "run", [*args[:1], good, *args[2:]], inputs=[good])


# =================================================================================================
# Item 8: measure --no-checksum and --columns, study --no-checksum
# =================================================================================================

def _measure(seeds, catalogue, *extra):
    return ["measure", seeds["frame"], "--catalog", catalogue, "--psf", seeds["psf"], *MEASURE_ARGS, *extra]


def test_measure_no_checksum(server, seeds, tmp_path):
    """A catalogue edited on purpose, its checksums left stale (astropy keeps the old cards): refused, and
    measured with the command's own --no-checksum (as render's and correlate's)."""
    stale = tmp_path / "stale.fits"
    with fits.open(seeds["truth"]) as hdul:
        copy = fits.HDUList([h.copy() for h in hdul])
    copy[1].data["mag_J129"][2] += 0.01            # a row off the frame: the shapes do not change
    copy.writeto(stale)                              # without checksum=True: CHECKSUM/DATASUM now stale
    refused(server, tmp_path, _measure(seeds, str(stale)), "stale.fits", "--no-checksum",
            inputs=[stale, *seeds.values()])
    run = accepted(server, tmp_path / "nocheck", _measure(seeds, str(stale), "--no-checksum"),
                   inputs=[stale, *seeds.values()])
    ref = accepted(server, tmp_path / "ref", _measure(seeds, seeds["truth"]), inputs=seeds.values())
    with fits.open(run["out"]) as a, fits.open(ref["out"]) as b:
        for column in ("id", "g1", "g2", "flags"):
            np.testing.assert_array_equal(a["SHAPES"].data[column], b["SHAPES"].data[column])


def test_measure_columns(server, seeds, tmp_path):
    """A SExtractor-style catalogue (NUMBER, ALPHA_J2000, DELTA_J2000) measured through --columns gives the
    shapes of the catalogue under perscli's names; without the mapping the error suggests it; a mapping of
    a column measure does not read is refused."""
    with fits.open(seeds["truth"]) as hdul:
        table = hdul[1].data
        renamed = {"id": "NUMBER", "ra": "ALPHA_J2000", "dec": "DELTA_J2000"}
        cols = [fits.Column(renamed.get(c.name, c.name), c.format, array=table[c.name], unit=c.unit)
                for c in hdul[1].columns]
    sex = tmp_path / "sex.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols)]).writeto(sex, checksum=True)
    mapping = "id=NUMBER,ra=ALPHA_J2000,dec=DELTA_J2000"
    run = accepted(server, tmp_path / "mapped", _measure(seeds, str(sex), "--columns", mapping),
                   inputs=[sex, *seeds.values()])
    ref = accepted(server, tmp_path / "ref", _measure(seeds, seeds["truth"]), inputs=seeds.values())
    with fits.open(run["out"]) as a, fits.open(ref["out"]) as b:
        assert len(a["SHAPES"].data) == len(b["SHAPES"].data) >= 1
        for column in ("id", "ra", "dec", "g1", "g2", "flags"):
            np.testing.assert_array_equal(a["SHAPES"].data[column], b["SHAPES"].data[column])
    refused(server, tmp_path / "bare", _measure(seeds, str(sex)), "sex.fits", "--columns id=",
            inputs=[sex])
    refused(server, tmp_path / "unread", _measure(seeds, str(sex), "--columns", f"{mapping},flux=mag_J129"),
            "--columns flux=mag_J129", inputs=[sex])


def test_study_takes_no_checksum_and_passes_it_to_its_tasks(tmp_path, monkeypatch):
    """--no-checksum on study reaches the run (its read options, which the runner carries to each task);
    the study itself is replaced by stubs, nothing is rendered."""
    from click.testing import CliRunner

    import perscli.study.config as config
    import perscli.study.plan as plan
    import perscli.study.runner as runner
    from perscli.cli.main import cli

    seen = []
    monkeypatch.setattr(config, "load_study", lambda description, preset=None, overrides=(): {"name": "stub"})
    monkeypatch.setattr(config, "dump", lambda s: "name: stub\n")
    monkeypatch.setattr(plan, "build", lambda s, **kw: [])
    monkeypatch.setattr(runner, "task_dicts", lambda tasks: [])
    from perscli.io.checksum import checksums_enabled

    monkeypatch.setattr(runner, "run_study", lambda tasks, outdir, options=None: seen.append(checksums_enabled()) or [])
    for flag, expected in (([], True), (["--no-checksum"], False)):
        result = CliRunner().invoke(cli, ["study", "--preset", "ci", "-o", str(tmp_path / "s"), *flag])
        assert result.exit_code == 0, result.output
        assert seen[-1] == expected


# =================================================================================================
# Item 9: count lines, the joint table's unit, figures
# =================================================================================================

def test_pointings_and_catalog_print_the_rows_written(server, tmp_path):
    """One line on stderr with the number of rows written, which is the table's; none with -q."""
    plan = ["pointings", "plan", "--ra", "10", "--dec", "-44", "--n", "3"]
    run = accepted(server, tmp_path / "p", plan)
    with fits.open(run["out"]) as hdul:
        rows = len(hdul["POINTINGS"].data)
    assert rows == 3 and run["stderr"] == f"{run['out']}: 3 rows written (exposures)\n"
    cat = ["catalog", "--ra", "10", "--dec", "-44", "--size", "0.5", "--star-density", "4", "--seed", "2"]
    run = accepted(server, tmp_path / "c", cat)
    with fits.open(run["out"]) as hdul:
        data = hdul["TRUTH"].data
        rows, galaxies = len(data), int(np.sum(np.char.strip(data["kind"]) == "galaxy"))
    lines = run["stderr"].splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{run['out']}: {rows} rows written ({galaxies} galaxies, "), \
        run["stderr"]
    assert 0 < galaxies < rows
    # to standard output: the count still goes to stderr, named 'stdout'
    piped = accepted(server, tmp_path / "s", [*plan, "-o", "-"], output=False)
    assert piped["stderr"] == "stdout: 3 rows written (exposures)\n" and piped["stdout"][:6] == b"SIMPLE"
    for args in (plan, cat):
        quiet = accepted(server, tmp_path / f"q{args[0]}", ["-q", *args])
        assert quiet["stderr"] == ""


def test_the_joint_table_reads_in_astropy_without_a_unit_warning(server, seeds, tmp_path):
    """flux was TUNIT 'electron/s', which astropy's FITS reader does not parse (UnitsWarning); FITS has no
    unit for electrons, so e-/s is said in the column's TTYPE comment."""
    from astropy.table import Table
    from astropy.units import UnitsWarning

    run = accepted(server, tmp_path, [*_measure(seeds, seeds["truth"]), "--joint"], inputs=seeds.values())
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnitsWarning)
        table = Table.read(run["out"], hdu="JOINT")
    assert table["T"].unit == "arcsec2" and table["flux"].unit is None and len(table) >= 1
    with fits.open(run["out"]) as hdul:
        header = hdul["JOINT"].header
        k = table.colnames.index("flux") + 1
        assert "e-/s" in header.comments[f"TTYPE{k}"] and f"TUNIT{k}" not in header


def _figure_of(monkeypatch, draw):
    """The matplotlib figure ``draw()`` makes (captured when it is closed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figures = []
    real_close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: figures.append(fig) or real_close(fig))
    draw()
    assert len(figures) == 1
    return figures[0]


@pytest.mark.parametrize("xip5", [5e-11, 5e-8])
def test_the_budget_legend_hides_no_point(monkeypatch, xip5):
    """The legend lies below the axes: with loc='best' it sat on the points at 4-6 arcmin.  With a bin over
    the budget (xip5 = 5e-8) the legend has four entries and the title, the longest verdict, stays inside
    the figure (wrapped at 95 characters it ran past the right edge)."""
    from perscli.stats.budget import XiTable, budget_figure, compare

    theta = np.geomspace(0.3, 10.0, 8)
    xi = XiTable(label="xi.fits", name="xi.fits", theta=theta, unit="arcmin",
                 xip=np.array([1e-10, 1e-10, 9e-11, 8e-11, 5e-11, 3e-8 if xip5 > 1e-9 else 1e-11, xip5, 8e-12]),
                 sigma_xip=np.full(8, 2e-12), empty=np.zeros(8, bool), var_method="jackknife")
    result = compare(xi, bands="dore2018", modes="EB" if xip5 > 1e-9 else "E", n_sigma=2.0)
    assert (result.n_exceeding > 0) == (xip5 > 1e-9)
    fig = _figure_of(monkeypatch, lambda: budget_figure(result))
    ax = fig.axes[0]
    legend = ax.get_legend()
    assert len(legend.get_texts()) == (4 if xip5 > 1e-9 else 3)
    assert legend.get_window_extent().y1 <= ax.get_window_extent().y0, "the legend overlaps the axes"
    # with a margin of 2% of the width: the extent is measured without the glyphs' overhang (at 95
    # characters it ended 8 pixels short of the edge, and the PNG lost the last characters)
    title, page = ax.title.get_window_extent(), fig.bbox
    margin = 0.02 * page.width
    assert page.x0 + margin <= title.x0 and title.x1 <= page.x1 - margin and title.y1 <= page.y1, (title, page)


def test_bin_theta_is_scaled_to_the_bins_with_objects(monkeypatch, tmp_path):
    """Three galaxies in one |De| bin (fractions of 1/3, error bars of 0.5) no longer set the y axis of
    2000 in another, whose fractions lie near 1/18."""
    from perscli.stats.de_stats import theta_distribution
    from perscli.stats.plots import theta_figure

    rng = np.random.default_rng(2)
    angle = rng.uniform(0, 2 * np.pi, 2003)
    amp = np.r_[10 ** rng.uniform(-6, -4, 2000), 10 ** rng.uniform(-4, -2, 3)]
    theta = theta_distribution(amp * np.cos(angle), amp * np.sin(angle), nboot=20, seed=1)
    big = (theta["de_lo"] == 1e-6) & (theta["n"] == 2000)
    fig = _figure_of(monkeypatch, lambda: theta_figure(theta, str(tmp_path / "bin_theta.png")))
    low, high = fig.axes[0].get_ylim()
    top = float(np.max(theta["frac"][big] + theta["frac_err"][big]))
    assert top <= high < 1.3 * top, (low, high, top)       # the 2000-galaxy bin fills the axis
    assert np.max(theta["frac"][~big & (theta["n"] == 3)]) > high  # the 3-galaxy bin's points lie beyond it
    assert (tmp_path / "bin_theta.png").stat().st_size > 0
    legend = fig.axes[0].get_legend()
    assert legend.get_window_extent().y1 <= fig.axes[0].get_window_extent().y0, "the legend overlaps the axes"
    assert [t.get_text().endswith("few objects, not to scale") for t in legend.get_texts()].count(True) == 1


def test_the_xi_legend_hides_no_point(monkeypatch, tmp_path):
    """correlate's xi.png: the legends sat in each panel's upper right corner, on the highest points at the
    largest separations; now one legend below the lower panel."""
    from perscli.stats.plots import xi_figure

    r = np.geomspace(0.5, 20, 10)
    high = np.full(10, 1e-10)
    xi = dict(meanr=r, xip=high, xim=high, sigma_xip=np.full(10, 1e-11), sigma_xim=np.full(10, 1e-11),
              npairs=np.full(10, 100), r_nom=r)
    fig = _figure_of(monkeypatch, lambda: xi_figure(xi, str(tmp_path / "xi.png"), title="De"))
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    assert len(legends) == 1 and len(legends[0].get_texts()) == 2
    bottom = min(ax.get_window_extent().y0 for ax in fig.axes)
    assert legends[0].get_window_extent().y1 <= bottom, "the legend overlaps the axes"
    assert (tmp_path / "xi.png").stat().st_size > 0
