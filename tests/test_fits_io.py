"""The FITS layer (fitsio underneath): every command reads .fits.gz, tile-compressed (fpack) and
file.fits[EXT] inputs as it reads the plain file; --compress and .gz outputs read back in astropy
and fitsio with valid checksums; checksum failures name the HDU; stdin, FIFOs and broken pipes.
"""

import gzip
import os
import shutil
import subprocess
import sys
import threading

import fitsio
import numpy as np
import pytest
from astropy.io import fits

from fits_factory import run
from test_render import DEC, FILTER, MJD1, MJD2, PA, RA, SCA, grid_objects, write_catalog

PERSCLI = shutil.which("perscli", path=os.path.dirname(sys.executable)) or shutil.which("perscli")
BOUNDS = (1001, 1096, 2001, 2096)


def render(truth, out, mjd, *extra, seed=1):
    return run("render", truth, "--ra", RA, "--dec", DEC, "--pa", PA, "--mjd", mjd, "--filter", FILTER,
               "--sca", SCA, "--bounds", *BOUNDS, "--seed", seed, "-o", out, *extra)


def gz(src, dest):
    with open(src, "rb") as fin, gzip.open(dest, "wb") as fout:
        fout.write(fin.read())
    return str(dest)


def fpack(src, dest):
    """Every image extension tile-compressed (lossless GZIP_2), header cards copied verbatim, as fpack does."""
    skip = ("SIMPLE", "XTENSION", "BITPIX", "NAXIS", "NAXIS1", "NAXIS2", "NAXIS3", "EXTEND", "PCOUNT", "GCOUNT",
            "CHECKSUM", "DATASUM", "EXTNAME", "BZERO", "BSCALE", "TFIELDS")
    with fitsio.FITS(str(src)) as fin, fitsio.FITS(str(dest), "rw", clobber=True, ignore_empty=True) as fout:
        for i, hdu in enumerate(fin):
            cards = [r["card_string"] for r in hdu.read_header_list()
                     if r["name"] not in skip and not str(r["name"]).startswith(("TTYPE", "TFORM", "TUNIT"))]
            data = hdu.read()
            name = hdu.get_extname() or None
            if hdu.get_exttype() == "IMAGE_HDU" and data is not None and i > 0:
                fout.write(np.ascontiguousarray(data.astype(data.dtype.newbyteorder("="))), extname=name,
                           compress="GZIP_2", qlevel=0.0)
            elif hdu.get_exttype() == "IMAGE_HDU":
                fout.write(data, extname=name)
            else:
                fout.write_table(data, extname=name)
            for card in cards:
                fout._FITS.write_record(len(fout), card)
            fout.update_hdu_list()
            fout[-1].write_checksum()
    return str(dest)


def science(path, ext="SCI"):
    with fits.open(path) as hdul:
        return np.asarray(hdul[ext].data, dtype=np.float64)


def table(path, ext=1):
    with fits.open(path) as hdul:
        return {n: np.asarray(hdul[ext].data[n]) for n in hdul[ext].columns.names}


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """A truth catalogue, two rendered exposures, their persistence, shapes, xi."""
    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    d = tmp_path_factory.mktemp("fitsio")
    optics = Optics(Exposure(ra=RA, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD1))
    objects = [(k, x, y, m, h, e1, e2) for (k, x, y, m, h, e1, e2) in grid_objects((1001, 1768, 2001, 2768))]
    objects = [(k, BOUNDS[0] + 20 + 25 * (i % 3), BOUNDS[2] + 20 + 25 * (i // 3), m if k == "galaxy" else 12.0,
                h, e1, e2) for i, (k, x, y, m, h, e1, e2) in enumerate(objects)]
    truth = write_catalog(d / "truth.fits", optics, objects)
    e1 = d / "e1.fits"
    e2 = d / "e2.fits"
    render(truth, e1, MJD1)
    render(truth, e2, MJD2, "--previous", e1, seed=2)
    return {"dir": d, "truth": truth, "e1": str(e1), "e2": str(e2)}


# -- every command reads .gz, fpack and [EXT] -----------------------------------------------------

def test_apply_persistence_reads_gz_fpack_and_ext(chain, tmp_path):
    e1, e2 = chain["e1"], chain["e2"]
    plain = run("apply-persistence", e2, e1, "--mode", "predict", "-o", tmp_path / "plain.fits")
    expected = science(tmp_path / "plain.fits")
    assert expected.max() > 1.0  # a bright star leaves persistence
    variants = {
        "gz": (gz(e2, tmp_path / "e2.fits.gz"), gz(e1, tmp_path / "e1.fits.gz")),
        "fpack": (fpack(e2, tmp_path / "e2.fz"), fpack(e1, tmp_path / "e1.fz")),
        # [FLUENCE] names the image that holds the earlier exposure's charge; [SCI] the current one
        "ext": (f"{e2}[SCI]", f"{e1}[FLUENCE]"),
    }
    for name, (cur, prev) in variants.items():
        out = tmp_path / f"{name}.fits"
        run("apply-persistence", cur, prev, "--mode", "predict", "-o", out)
        np.testing.assert_allclose(science(out), expected, rtol=1e-6, atol=1e-9, err_msg=name)
    del plain


def test_image_section_shifts_ltv_and_takes_the_same_pixels(chain, tmp_path):
    e1, e2 = chain["e1"], chain["e2"]
    run("apply-persistence", e2, e1, "--mode", "predict", "-o", tmp_path / "plain.fits")
    run("apply-persistence", f"{e2}[SCI][11:40,21:60]", f"{e1}[FLUENCE][11:40,21:60]", "--mode", "predict",
        "-o", tmp_path / "cut.fits")
    np.testing.assert_allclose(science(tmp_path / "cut.fits"), science(tmp_path / "plain.fits")[20:60, 10:40],
                               rtol=1e-6, atol=1e-9)
    # sections one column apart are placed on their shared detector pixels (LTV1/LTV2): the current
    # frame's first column has no earlier pixel under it
    run("apply-persistence", f"{e2}[SCI][11:40,21:60]", f"{e1}[FLUENCE][12:41,21:60]", "--mode",
        "predict", "-o", tmp_path / "shifted.fits")
    got, plain = science(tmp_path / "shifted.fits"), science(tmp_path / "plain.fits")
    np.testing.assert_allclose(got[:, 1:], plain[20:60, 10:40][:, 1:], rtol=1e-6, atol=1e-9)
    assert np.all(got[:, 0] == 0)


def test_measure_and_render_read_gz_fpack_and_ext(chain, tmp_path):
    truth, e2 = chain["truth"], chain["e2"]
    run("measure", e2, "--catalog", truth, "-o", tmp_path / "plain.fits")
    expected = table(tmp_path / "plain.fits")
    assert np.isfinite(expected["g1"]).any()
    for name, (frame, cat) in {"gz": (gz(e2, tmp_path / "e2.fits.gz"), gz(truth, tmp_path / "t.fits.gz")),
                               "fpack": (fpack(e2, tmp_path / "e2.fz"), truth),
                               "ext": (f"{e2}[SCI]", f"{truth}[1]")}.items():
        out = tmp_path / f"{name}.fits"
        run("measure", frame, "--catalog", cat, "-o", out)
        got = table(out)
        np.testing.assert_array_equal(got["flags"], expected["flags"], err_msg=name)
        np.testing.assert_allclose(got["g1"], expected["g1"], rtol=1e-9, atol=1e-12, err_msg=name)
    render(gz(truth, tmp_path / "truth.fits.gz"), tmp_path / "r_gz.fits", MJD1)
    render(f"{truth}[1]", tmp_path / "r_ext.fits", MJD1)
    for name in ("r_gz.fits", "r_ext.fits"):
        np.testing.assert_array_equal(science(tmp_path / name), science(chain["e1"]))


def test_correlate_and_budget_read_gz_and_ext(chain, tmp_path):
    rng = np.random.default_rng(4)
    n = 400
    cols = [fits.Column(name="id", format="K", array=np.arange(n)),
            fits.Column(name="ra", format="D", array=10 + rng.uniform(0, 0.5, n)),
            fits.Column(name="dec", format="D", array=-44 + rng.uniform(0, 0.5, n)),
            fits.Column(name="de1", format="D", array=rng.normal(0, 1e-6, n)),
            fits.Column(name="de2", format="D", array=rng.normal(0, 1e-6, n))]
    path = tmp_path / "de.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(cols, name="DE")]).writeto(path, checksum=True)
    common = ["--de1", "de1", "--de2", "de2", "--npatch", "4", "--nbins", "5"]
    run("correlate", path, *common, "-o", tmp_path / "xi.fits")
    expected = table(tmp_path / "xi.fits", "XI")
    for name, src in {"gz": gz(path, tmp_path / "de.fits.gz"), "ext": f"{path}[DE]"}.items():
        run("correlate", src, *common, "-o", tmp_path / f"xi_{name}.fits")
        np.testing.assert_allclose(table(tmp_path / f"xi_{name}.fits", "XI")["xip"], expected["xip"], rtol=1e-12)
    run("budget", gz(tmp_path / "xi.fits", tmp_path / "xi.fits.gz"), "-o", tmp_path / "b_gz.fits")
    run("budget", f"{tmp_path / 'xi.fits'}[XI]", "-o", tmp_path / "b_ext.fits")
    np.testing.assert_array_equal(table(tmp_path / "b_gz.fits", "BUDGET")["xip"],
                                  table(tmp_path / "b_ext.fits", "BUDGET")["xip"])


def test_catalog_and_pointings_read_gz_inputs(tmp_path, shared_data):
    gaia = shared_data / "gaia" / "145650.fits"
    run("catalog", "--ra", 10.05, "--dec", -43.8, "--size", 3, "--gaia", gaia, "-o", tmp_path / "a.fits")
    run("catalog", "--ra", 10.05, "--dec", -43.8, "--size", 3, "--gaia", gz(gaia, tmp_path / "g.fits.gz"),
        "-o", tmp_path / "b.fits")
    np.testing.assert_array_equal(table(tmp_path / "a.fits")["ra"], table(tmp_path / "b.fits")["ra"])
    sched = shared_data / "roman" / "Roman_WAS_obseq_11_1_23.fits"
    args = ["--ra", 10, "--dec", -44, "--radius", 0.2, "--filter", "J129"]
    run("pointings", "select", "--schedule", sched, *args, "-o", tmp_path / "p1.fits")
    run("pointings", "select", "--schedule", f"{gz(sched, tmp_path / 's.fits.gz')}[1]", *args, "-o", tmp_path / "p2.fits")
    np.testing.assert_array_equal(table(tmp_path / "p1.fits")["mjd"], table(tmp_path / "p2.fits")["mjd"])


# -- compressed outputs ---------------------------------------------------------------------------

@pytest.mark.parametrize("how", ["--compress gzip", ".gz", "--compress gzip .gz"])
def test_compressed_outputs_verify_in_astropy_and_fitsio(chain, tmp_path, how):
    out = tmp_path / ("out.fits.gz" if ".gz" in how else "out.fits")
    extra = ["--compress", "gzip"] if "--compress" in how else []
    render(chain["truth"], out, MJD2, "--previous", chain["e1"], *extra, seed=2)
    with fits.open(out, checksum=True) as hdul:
        hdul.verify("exception")
        for name in ("SCI", "IDEAL", "FLUENCE", "PERSIST"):
            np.testing.assert_array_equal(hdul[name].data, science(chain["e2"], name))
            if "--compress" in how:
                assert isinstance(hdul[name], fits.CompImageHDU)
    plain = out.with_suffix("") if str(out).endswith(".gz") else out
    if str(out).endswith(".gz"):
        with gzip.open(out) as fin, open(plain, "wb") as fout:
            fout.write(fin.read())
    with fitsio.FITS(str(plain)) as f:
        for hdu in f:
            hdu.verify_checksum()  # raises on a mismatch
        np.testing.assert_array_equal(f["SCI"].read(), science(chain["e2"]))


def test_compression_is_lossless_and_at_most_half_the_size(chain, tmp_path):
    """A 1024^2 cutout (the full SCA behaves the same per pixel; benchmarks/RESULTS.md has the full SCA)."""
    args = ["--bounds", 1001, 2024, 2001, 3024]
    plain, packed = tmp_path / "plain.fits", tmp_path / "packed.fits"
    for out, extra in ((plain, []), (packed, ["--compress", "gzip"])):
        run("render", chain["truth"], "--ra", RA, "--dec", DEC, "--pa", PA, "--mjd", MJD2, "--filter", FILTER,
            "--sca", SCA, *args, "--seed", 2, "-o", out, *extra)
    assert os.path.getsize(packed) <= 0.5 * os.path.getsize(plain)
    for name in ("SCI", "IDEAL", "FLUENCE"):
        np.testing.assert_array_equal(science(packed, name), science(plain, name))


def test_same_content_same_bytes_even_gzipped(chain, tmp_path):
    outs = []
    for k in range(2):
        out = tmp_path / f"o{k}.fits.gz"
        run("apply-persistence", chain["e2"], chain["e1"], "-o", out)
        with gzip.open(out) as fh:
            raw = fh.read()
        outs.append(b"".join(raw[i:i + 80] for i in range(0, len(raw), 80)
                             if raw[i:i + 8] not in (b"DATE    ", b"CHECKSUM")))
    assert outs[0] == outs[1]


# -- checksums ------------------------------------------------------------------------------------

def flip(src, dest, offset):
    data = bytearray(open(src, "rb").read())
    data[offset] ^= 0x01
    open(dest, "wb").write(data)
    return str(dest)


def test_a_flipped_bit_in_ideal_or_fluence_is_caught_and_names_the_hdu(chain, tmp_path):
    def offsets(path):
        with fitsio.FITS(path) as f:
            return {f[i].get_extname(): f[i].get_offsets() for i in range(len(f))}

    # the earlier exposure's FLUENCE is used; the current one's IDEAL is copied into the output
    for path, name, role in ((chain["e1"], "FLUENCE", "earlier"), (chain["e2"], "IDEAL", "current")):
        bad = flip(path, tmp_path / f"bad_{name}.fits", offsets(path)[name]["data_start"] + 1001)
        args = [chain["e2"], bad] if role == "earlier" else [bad, chain["e1"]]
        result = run("apply-persistence", *args, "-o", tmp_path / "o.fits", code=1)
        assert f"({name})" in result.stderr and "DATASUM" in result.stderr, result.stderr
        assert not (tmp_path / "o.fits").exists()
    # a header bit of the earlier exposure's SCI (whose timing keywords are used) is caught by CHECKSUM
    # although its data are not read; --no-checksum lets it through.  The bit is in the last digit of
    # CD1_1's value, so that the card stays valid FITS: a flip that makes it invalid (CD1_1 -> CD1^1) is
    # refused even with --no-checksum (tests/test_fuzz_faults.py)
    header_at = offsets(chain["e1"])["SCI"]["header_start"] + 80 * 12 + 29
    bad = flip(chain["e1"], tmp_path / "hdr.fits", header_at)
    result = run("apply-persistence", chain["e2"], bad, "--mode", "predict", "-o", tmp_path / "o.fits", code=1)
    assert "(SCI)" in result.stderr and "CHECKSUM" in result.stderr and "--no-checksum" in result.stderr
    run("--no-checksum", "apply-persistence", chain["e2"], bad, "--mode", "predict", "-o", tmp_path / "o.fits")
    # passed down, not left behind: the next command in this process verifies again
    result = run("apply-persistence", chain["e2"], bad, "--mode", "predict", "-o", tmp_path / "o.fits",
                 "--overwrite", code=1)
    assert "CHECKSUM" in result.stderr


def test_a_rendered_frame_is_accepted_as_current(chain, tmp_path):
    """The regression of issue 8: SCI's sum was compared with FLUENCE's DATASUM."""
    for mode in ("add", "subtract", "predict"):
        run("apply-persistence", chain["e2"], chain["e1"], "--mode", mode, "-o", tmp_path / f"{mode}.fits")
    sci = science(chain["e2"])
    np.testing.assert_allclose(science(tmp_path / "add.fits") - sci, science(tmp_path / "predict.fits"),
                               atol=1e-3 + 1e-6 * np.abs(sci).max())
    np.testing.assert_allclose(sci - science(tmp_path / "subtract.fits"), science(tmp_path / "predict.fits"),
                               atol=1e-3 + 1e-6 * np.abs(sci).max())


# -- streams ----------------------------------------------------------------------------------------

@pytest.mark.skipif(PERSCLI is None, reason="perscli console script not installed")
def test_fifo_with_a_writer_is_read_and_without_one_is_an_error(chain, tmp_path):
    fifo = tmp_path / "pipe.fits"
    os.mkfifo(fifo)
    data = open(chain["e2"], "rb").read()

    def writer():
        with open(fifo, "wb") as fh:
            fh.write(data)

    thread = threading.Thread(target=writer)
    thread.start()
    proc = subprocess.run([PERSCLI, "apply-persistence", str(fifo), chain["e1"], "--mode", "predict", "-o",
                           str(tmp_path / "o.fits")], capture_output=True, text=True, timeout=60)
    thread.join(10)
    assert proc.returncode == 0, proc.stderr
    proc = subprocess.run([PERSCLI, "apply-persistence", str(fifo), chain["e1"], "-o", str(tmp_path / "p.fits")],
                          capture_output=True, text=True, timeout=60, env={**os.environ, "PERSCLI_FIFO_TIMEOUT": "1"})
    assert proc.returncode == 1 and "FIFO" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "p.fits").exists()


@pytest.mark.skipif(PERSCLI is None, reason="perscli console script not installed")
def test_broken_stdout_pipe_is_quiet(chain):
    proc = subprocess.run(["bash", "-o", "pipefail", "-c",
                           f"{PERSCLI} apply-persistence {chain['e2']} {chain['e1']} -o - | head -c 100 > /dev/null"],
                          capture_output=True, text=True, timeout=60)
    assert "Traceback" not in proc.stderr and "Error" not in proc.stderr


@pytest.mark.skipif(PERSCLI is None, reason="perscli console script not installed")
def test_gzipped_stdin(chain, tmp_path):
    cmd = (f"gzip -c {chain['e2']} | {PERSCLI} apply-persistence - {chain['e1']} --mode predict "
           f"-o {tmp_path / 'o.fits'}")
    proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    run("apply-persistence", chain["e2"], chain["e1"], "--mode", "predict", "-o", tmp_path / "p.fits")
    np.testing.assert_array_equal(science(tmp_path / "o.fits"), science(tmp_path / "p.fits"))


def test_the_fast_writer_and_fitsio_write_the_same_file(tmp_path, monkeypatch):
    """The hand-written path for plain images (kept for speed) against the fitsio path."""
    import perscli.io.fitsfile as fitsfile
    from perscli.io.fitsfile import OutHDU, write_fits_path
    from perscli.io.cards import format_card

    rng = np.random.default_rng(2)
    cards = [format_card("BUNIT", "electron"), format_card("EXPSTART", 61541.123456789012),
             format_card("LONGNAME", "x" * 150, "a long string"), format_card("HISTORY", "made here")]
    hdus = [OutHDU([format_card("CREATOR", "test")]),
            OutHDU(cards, rng.normal(0, 1, (37, 53)).astype(">f4"), extname="SCI"),
            OutHDU(list(cards), rng.integers(-5, 5, (4, 6, 7)).astype(np.int16), extname="DQ"),
            OutHDU([format_card("EXTNAME", "EMPTY")], None)]
    write_fits_path(hdus, str(tmp_path / "fast.fits"))
    monkeypatch.setattr(fitsfile, "_plain_image", lambda data: False)
    write_fits_path(hdus, str(tmp_path / "cfitsio.fits"))

    def content(path):
        with fits.open(path, checksum=True) as hdul:
            hdul.verify("exception")
            return [(h.name, None if h.data is None else h.data.tolist(),
                     [(k, v) for k, v in h.header.items() if k not in ("COMMENT", "CHECKSUM")]) for h in hdul]

    assert content(tmp_path / "fast.fits") == content(tmp_path / "cfitsio.fits")
    with fitsio.FITS(str(tmp_path / "fast.fits")) as f:
        for hdu in f:
            hdu.verify_checksum()
        assert f["SCI"].read_header()["EXPSTART"] == 61541.123456789012
