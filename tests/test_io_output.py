"""perscli.io.output: refusing outputs, atomic checksummed writes, provenance, reproducible outputs."""

import datetime as dt
import io
import os
import re
import stat
import sys
import warnings

import numpy as np
import pytest
from astropy.io import fits

import perscli
from perscli import PerscliError
from perscli.io.output import CREATOR, add_provenance, check_output
from perscli.io.output import atomic_output, atomic_path, write_hdus
from perscli.io.tempfiles import make_temp_file, make_temp_folder

from fits_factory import (DAY, SHAPE, T0, cards_except, cube_file, frame_file, image_file, invoke, listing,
                          raw_cards_masked, timing, wfc3_ramp_file)


def small_hdul(value=1.0):
    from perscli.io.fitsfile import OutHDU
    from perscli.io.cards import format_card

    return [OutHDU([format_card("OBJECT", "test")]), OutHDU([], np.full(SHAPE, value, dtype=np.float32), extname="SCI")]


def open_verified(path):
    """Open with checksum verification, every warning (a bad CHECKSUM/DATASUM, a fixed card) an error."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hdul = fits.open(path, checksum=True)
        for hdu in hdul:
            _ = hdu.data
    return hdul


@pytest.fixture
def failing_writer(monkeypatch):
    """Make the FITS writer fail at its second HDU, as a full disk or a bug mid-file would."""
    import perscli.io.fitsfile as fitsfile

    real = fitsfile._header_cards
    state = {"exc": OSError, "calls": 0}

    def header_cards(cards):
        state["calls"] += 1
        if state["calls"] > 1:
            raise state["exc"]("simulated failure while writing")
        return real(cards)

    monkeypatch.setattr(fitsfile, "_header_cards", header_cards)
    return state


# -- check_output ------------------------------------------------------------------------------

def test_check_output_accepts_a_new_file(tmp_path):
    check_output(str(tmp_path / "new.fits"))
    assert listing(tmp_path) == []


def test_check_output_refuses_an_existing_file(tmp_path):
    dest = tmp_path / "out.fits"
    dest.write_bytes(b"old")
    with pytest.raises(PerscliError) as err:
        check_output(str(dest))
    assert str(dest) in str(err.value) and "--overwrite" in str(err.value)
    check_output(str(dest), overwrite=True)            # allowed with overwrite
    assert dest.read_bytes() == b"old"


@pytest.mark.parametrize("overwrite", [False, True])
def test_check_output_refuses_an_input(tmp_path, overwrite):
    src = frame_file(tmp_path / "in.fits")
    with pytest.raises(PerscliError, match="is also an input"):
        check_output(src, overwrite=overwrite, inputs=[str(tmp_path / "other.fits"), src])


def test_check_output_recognises_an_input_under_another_name(tmp_path, monkeypatch):
    src = frame_file(tmp_path / "in.fits")
    os.symlink(src, tmp_path / "link.fits")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(PerscliError, match="is also an input"):
        check_output("link.fits", overwrite=True, inputs=["./in.fits"])


def test_check_output_refuses_a_missing_folder(tmp_path):
    dest = tmp_path / "no" / "such" / "out.fits"
    with pytest.raises(PerscliError) as err:
        check_output(str(dest))
    assert "does not exist" in str(err.value) and str(tmp_path / "no" / "such") in str(err.value)


def test_check_output_refuses_a_terminal_for_stdout(monkeypatch):
    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stdout", Tty())
    with pytest.raises(PerscliError, match="terminal"):
        check_output("-")


def test_check_output_accepts_a_pipe_for_stdout(monkeypatch):
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    check_output("-")


# -- write_hdus --------------------------------------------------------------------------------

def test_write_hdus_writes_verified_checksums_and_leaves_no_temporary_file(tmp_path):
    dest = tmp_path / "out.fits"
    write_hdus(small_hdul(3.0), str(dest))
    assert listing(tmp_path) == ["out.fits"]
    with open_verified(dest) as hdul:
        for hdu in hdul:
            assert "CHECKSUM" in hdu.header and "DATASUM" in hdu.header
        assert hdul[1].header["DATASUM"] != "0"
        np.testing.assert_array_equal(hdul["SCI"].data, 3.0)


# -- permissions: those of any new file (0666 less the umask), not mkstemp's 0600 -----------------

@pytest.fixture(params=[(0o022, 0o644), (0o077, 0o600), (0o027, 0o640)], ids=["022", "077", "027"])
def umask(request):
    """Run under a umask; the value is the mode a new file gets under it."""
    mask, mode = request.param
    old = os.umask(mask)
    yield mode
    os.umask(old)


def mode_of(path):
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("name", ["out.fits", "out.fits.gz"])
def test_write_hdus_gives_the_file_ordinary_permissions(tmp_path, umask, name):
    dest = tmp_path / name
    write_hdus(small_hdul(), str(dest))
    assert mode_of(dest) == umask
    write_hdus(small_hdul(2.0), str(dest), overwrite=True)
    assert mode_of(dest) == umask
    assert listing(tmp_path) == [name]


def test_atomic_output_and_atomic_path_give_ordinary_permissions(tmp_path, umask):
    with atomic_output(str(tmp_path / "figure.png")) as fh:
        fh.write(b"png")
    with atomic_path(str(tmp_path / "regions.reg"), suffix=".part.reg") as tmp:
        with open(tmp, "w") as fh:               # as a library that writes to a path (matplotlib, ds9) does
            fh.write("fk5\n")
    assert {name: mode_of(tmp_path / name) for name in listing(tmp_path)} == {"figure.png": umask,
                                                                               "regions.reg": umask}


def test_temporary_files_and_folders_are_made_with_ordinary_permissions(tmp_path, umask):
    fd, path = make_temp_file(str(tmp_path), suffix=".part.png")
    os.close(fd)
    assert os.path.basename(path).startswith(".perscli-") and path.endswith(".part.png")
    assert mode_of(path) == umask
    folder = make_temp_folder(str(tmp_path), prefix=".perscli-diagnose-")
    assert os.path.isdir(folder) and mode_of(folder) == umask | ((umask & 0o444) >> 2)      # r implies x
    names = {os.path.basename(make_temp_file(str(tmp_path))[1]) for _ in range(50)}
    assert len(names) == 50


def test_temporary_file_names_are_never_reused(tmp_path, monkeypatch):
    import perscli.io.output as output

    tokens = iter(["aaaa", "aaaa", "bbbb"])
    monkeypatch.setattr(output.secrets, "token_hex", lambda n: next(tokens))
    fd1, first = make_temp_file(str(tmp_path))
    fd2, second = make_temp_file(str(tmp_path))      # 'aaaa' exists: the next name is taken
    os.close(fd1), os.close(fd2)
    assert (os.path.basename(first), os.path.basename(second)) == (".perscli-aaaa.part", ".perscli-bbbb.part")


def test_writing_never_changes_the_umask_even_for_a_moment(tmp_path, monkeypatch):
    # reading the umask means setting it (os.umask(0)), which other threads would see: never done
    calls = []
    monkeypatch.setattr(os, "umask", lambda mask: calls.append(mask))
    write_hdus(small_hdul(), str(tmp_path / "out.fits.gz"))
    with atomic_output(str(tmp_path / "x.png")) as fh:
        fh.write(b"png")
    assert calls == []


def test_write_hdus_refuses_an_existing_file_without_overwrite(tmp_path):
    dest = tmp_path / "out.fits"
    dest.write_bytes(b"old")
    with pytest.raises(PerscliError, match="--overwrite"):
        write_hdus(small_hdul(), str(dest))
    assert dest.read_bytes() == b"old"
    assert listing(tmp_path) == ["out.fits"]


def test_write_hdus_overwrite_replaces_the_file(tmp_path):
    dest = tmp_path / "out.fits"
    dest.write_bytes(b"old")
    write_hdus(small_hdul(7.0), str(dest), overwrite=True)
    with open_verified(dest) as hdul:
        np.testing.assert_array_equal(hdul["SCI"].data, 7.0)
    assert listing(tmp_path) == ["out.fits"]


@pytest.mark.parametrize("exc", [OSError, ValueError, KeyboardInterrupt])
def test_write_hdus_failure_leaves_nothing_behind(tmp_path, exc, failing_writer):
    failing_writer["exc"] = exc
    with pytest.raises(exc, match="simulated"):
        write_hdus(small_hdul(), str(tmp_path / "out.fits"))
    assert listing(tmp_path) == []


def test_write_hdus_failure_keeps_the_old_file(tmp_path, monkeypatch):
    dest = tmp_path / "out.fits"
    write_hdus(small_hdul(1.0), str(dest))
    before = dest.read_bytes()
    import perscli.io.fitsfile as fitsfile

    def broken(*args, **kwargs):
        raise OSError("simulated failure while writing")

    monkeypatch.setattr(fitsfile, "_header_cards", broken)
    with pytest.raises(OSError, match="simulated"):
        write_hdus(small_hdul(2.0), str(dest), overwrite=True)
    assert dest.read_bytes() == before
    assert listing(tmp_path) == ["out.fits"]


def test_write_hdus_failure_inside_the_checksum_pass_leaves_nothing_behind(tmp_path, monkeypatch):
    import perscli.io.fitsfile as fitsfile

    def broken(value):
        raise RuntimeError("simulated: disk full")

    monkeypatch.setattr(fitsfile, "_ascii_checksum", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        write_hdus(small_hdul(), str(tmp_path / "out.fits"))
    assert listing(tmp_path) == []


def test_write_hdus_to_stdout(tmp_path):
    stream = io.BytesIO()
    write_hdus(small_hdul(5.0), "-", stdout=stream)
    path = tmp_path / "piped.fits"
    path.write_bytes(stream.getvalue())
    assert len(stream.getvalue()) % 2880 == 0
    with open_verified(path) as hdul:
        np.testing.assert_array_equal(hdul["SCI"].data, 5.0)
    assert listing(tmp_path) == ["piped.fits"]


# -- add_provenance ----------------------------------------------------------------------------

def test_add_provenance_records_creator_date_history_params_and_inputs():
    assert CREATOR == f"perscli {perscli.__version__}"
    header = fits.Header()
    before = dt.datetime.now(dt.timezone.utc).replace(microsecond=0, tzinfo=None)
    add_provenance(header, step="apply-persistence mode=add", params={"PSMODE": ("add", "mode"), "PSN": 3},
                   inputs=[("PSCUR", "/some/dir/cur.fits", 12345), ("PSP01", "-", 7)], seed=42)
    after = dt.datetime.now(dt.timezone.utc).replace(tzinfo=None)
    assert header["CREATOR"] == f"perscli {perscli.__version__}"
    written = dt.datetime.strptime(header["DATE"], "%Y-%m-%dT%H:%M:%S")
    assert before <= written <= after
    assert header["PSMODE"] == "add" and header.comments["PSMODE"] == "mode"
    assert header["PSN"] == 3
    assert header["PSCUR"] == "cur.fits"
    assert header["PSCURDS"] == "12345"
    assert header["PSP01"] == "stdin"
    assert header["PSP01DS"] == "7"
    assert header["SEED"] == 42
    history = list(header["HISTORY"])
    assert history[0] == f"perscli {perscli.__version__}: apply-persistence mode=add"
    assert "".join(history[1:]) == ("  inputs: PSCUR=cur.fits (DATASUM 12345), PSP01=stdin (DATASUM 7), "
                                    "seed=42")


# -- provenance and reproducibility of apply-persistence ----------------------------------------

@pytest.fixture
def run_inputs(tmp_path):
    rng = np.random.default_rng(4)
    older = frame_file(tmp_path / "older.fits", rng.uniform(0, 8e4, SHAPE), start=T0, exptime=139.8)
    newer = frame_file(tmp_path / "newer.fits", rng.uniform(0, 8e4, SHAPE).astype(np.float32),
                       start=T0 + 300.0 / DAY, exptime=139.8, bunit="ELECTRONS")
    current = frame_file(tmp_path / "current.fits", rng.normal(10.0, 1.0, SHAPE).astype(np.float32),
                         start=T0 + 600.0 / DAY, exptime=100.0, bunit="electron/s", checksum=True)
    return current, newer, older


def apply(current, *previous, out, extra=()):
    result = invoke("apply-persistence", current, *previous, "-o", out, *extra)
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result


def astropy_datasum(path, index=1):
    # every HDU of the file checksummed by astropy itself
    with fits.open(path) as hdul:
        hdul.writeto(str(path) + ".sum.fits", checksum=True)
    with fits.open(str(path) + ".sum.fits") as hdul:
        value = hdul[index].header["DATASUM"]
    os.unlink(str(path) + ".sum.fits")
    return value


def test_apply_persistence_output_has_provenance(tmp_path, run_inputs):
    current, newer, older = run_inputs
    out = tmp_path / "out.fits"
    apply(current, older, newer, out=out, extra=["--set", "persistence.gamma=1.1"])
    with open_verified(out) as hdul:
        hdr = hdul[0].header
        assert hdr["CREATOR"] == f"perscli {perscli.__version__}"
        written = dt.datetime.strptime(hdr["DATE"], "%Y-%m-%dT%H:%M:%S")
        assert abs((dt.datetime.now(dt.timezone.utc).replace(tzinfo=None) - written).total_seconds()) < 120
        history = " ".join(hdr["HISTORY"])
        assert f"perscli {perscli.__version__}: apply-persistence mode=add" in history
        assert "gamma=1.1" in history
        assert hdr["PSMODE"] == "add"
        assert hdr["PSMODEL"] == "typical+gamma=1.1"
        assert hdr["PS_GAMMA"] == 1.1
        assert hdr["PSNPREV"] == 2
        assert hdr["PSUNIT"] == "electron/s"
        assert hdr["PSCUR"] == "current.fits"
        assert hdr["PSP01"] == "newer.fits"          # the most recent earlier exposure first
        assert hdr["PSP02"] == "older.fits"
        assert hdr["PSP01DT"] == pytest.approx(300.0 - 139.8, abs=1e-3)
        assert hdr["PSP02DT"] == pytest.approx(600.0 - 139.8, abs=1e-3)
        # the input checksums are astropy's own DATASUM of each input's science data
        with fits.open(current) as cur:
            assert hdr["PSCURDS"] == cur[1].header["DATASUM"]
        assert hdr["PSP01DS"] == astropy_datasum(newer)
        assert hdr["PSP02DS"] == astropy_datasum(older)
        for hdu in hdul:
            assert "CHECKSUM" in hdu.header and "DATASUM" in hdu.header
    assert sorted(listing(tmp_path)) == ["current.fits", "newer.fits", "older.fits", "out.fits"]


def test_apply_persistence_output_keeps_structure_and_units(tmp_path, run_inputs):
    current, newer, older = run_inputs
    out = tmp_path / "out.fits"
    apply(current, older, newer, out=out)
    with fits.open(out) as hdul, fits.open(current) as cur:
        assert [h.name for h in hdul] == [h.name for h in cur]
        assert hdul[1].header["BUNIT"] == "electron/s"
        assert hdul[1].header["EXPSTART"] == cur[1].header["EXPSTART"]
        assert hdul[1].data.dtype == np.dtype(">f4")
        assert np.all(hdul[1].data >= cur[1].data) and np.any(hdul[1].data > cur[1].data)


def test_apply_persistence_is_reproducible(tmp_path, run_inputs):
    current, newer, older = run_inputs
    out1, out2 = tmp_path / "run1.fits", tmp_path / "run2.fits"
    apply(current, older, newer, out=out1)
    apply(current, older, newer, out=out2)
    assert cards_except(out1) == cards_except(out2)
    with fits.open(out1) as a, fits.open(out2) as b:
        assert len(a) == len(b)
        for ha, hb in zip(a, b):
            if ha.data is not None:
                assert ha.data.tobytes() == hb.data.tobytes()
    # byte for byte, apart from the DATE and CHECKSUM card images
    assert os.path.getsize(out1) == os.path.getsize(out2)
    assert raw_cards_masked(out1) == raw_cards_masked(out2)
    with fits.open(out1) as a:
        assert "DATE" in a[0].header and "CHECKSUM" in a[0].header


def test_order_of_earlier_exposures_on_the_command_line_does_not_matter(tmp_path, run_inputs):
    current, newer, older = run_inputs
    out1, out2 = tmp_path / "run1.fits", tmp_path / "run2.fits"
    apply(current, older, newer, out=out1)
    apply(current, newer, older, out=out2)
    assert raw_cards_masked(out1) == raw_cards_masked(out2)


def _layout_file(tmp_path, layout):
    start = T0 + 1000.0 / DAY
    reads = [np.full(SHAPE, 100.0 * k, dtype=np.float32) for k in range(4)]
    if layout == "wfc3-ramp":
        return wfc3_ramp_file(tmp_path / "raw.fits", reads, [0.0, 10.0, 20.0, 30.0], {"BUNIT": "electron"},
                              primary_keywords=timing(start, 30.0))
    if layout == "cube":
        return cube_file(tmp_path / "cube.fits", np.stack(reads), [0.0, 10.0, 20.0, 30.0],
                         {"BUNIT": "electron", **timing(start, 30.0)})
    if layout == "primary":
        return image_file(tmp_path / "prim.fits", np.full(SHAPE, 5.0), {"BUNIT": "electron", **timing(start)},
                          primary=True)
    return image_file(tmp_path / "int.fits", np.full(SHAPE, 40000, dtype=np.uint16),
                      {"BUNIT": "DN", "GAIN": 2.0, **timing(start)})


@pytest.mark.parametrize("layout", ["wfc3-ramp", "cube", "primary", "uint16"])
def test_output_keeps_the_structure_of_every_layout(tmp_path, layout):
    current = _layout_file(tmp_path, layout)
    prev = frame_file(tmp_path / "prev.fits", np.full(SHAPE, 3e4), start=T0)
    out = tmp_path / "out.fits"
    apply(current, prev, out=out)
    increased = False
    with open_verified(out) as got, fits.open(current) as given:
        assert [(h.name, h.ver) for h in got] == [(h.name, h.ver) for h in given]
        for a, b in zip(got, given):
            if a.name in ("ERR", "DQ", "READTIMES"):           # passed through untouched
                assert a.data.tobytes() == b.data.tobytes()
                assert a.data.dtype == b.data.dtype
            elif b.data is not None:                            # science: float, persistence added
                assert a.data.dtype.kind == "f"
                assert a.data.shape == b.data.shape
                assert np.all(a.data >= np.asarray(b.data, dtype=np.float64))
                increased |= bool(np.any(a.data > np.asarray(b.data, dtype=np.float64)))
                assert "BZERO" not in a.header and "BSCALE" not in a.header
    assert increased          # (the zeroth read of a ramp, at t = 0, gets none)


def test_long_input_names_are_recorded_in_full(tmp_path):
    name = "hst_16000_01_wfc3_ir_f160w_iexample01_flt_with_a_rather_long_processing_suffix_v2.fits"
    prev = frame_file(tmp_path / name, np.full(SHAPE, 3e4), start=T0)
    current = frame_file(tmp_path / "current.fits", start=T0 + 300.0 / DAY)
    out = tmp_path / "out.fits"
    apply(current, prev, out=out)
    with open_verified(out) as hdul:
        assert hdul[0].header["PSP01"] == name


def test_a_chained_run_leaves_no_stale_provenance(tmp_path):
    prevs = [frame_file(tmp_path / f"p{i}.fits", np.full(SHAPE, 3e4), start=T0 + i * 200.0 / DAY)
             for i in range(3)]
    current = frame_file(tmp_path / "current.fits", start=T0 + 1000.0 / DAY)
    first = tmp_path / "first.fits"
    apply(current, *prevs, out=first)
    second = tmp_path / "second.fits"
    apply(first, prevs[0], out=second)
    with open_verified(second) as hdul:
        hdr = hdul[0].header
        assert hdr["PSNPREV"] == 1
        assert hdr["PSCUR"] == "first.fits"
        stale = [k for k in hdr if re.fullmatch(r"PSP(0[2-9]|[1-9]\d)\w*", k)]
        assert stale == []
        # the history keeps both steps and the inputs of each
        history = "".join(hdr["HISTORY"])
        assert history.count("apply-persistence mode=add") == 2
        assert history.count("=p2.fits (DATASUM") == 1 and history.count("=p0.fits (DATASUM") == 2
        assert "PSCUR=current.fits" in history
        assert "PSCUR=first.fits" in history
