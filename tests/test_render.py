"""perscli render: fluxes through the zeropoint, WCS round trips, every detector effect as defined,
reproducibility, persistence pairs, output structure and errors.

Objects are placed at chosen SCA pixels with the renderer's own GalSim WCS; cutouts (--bounds)
keep every render under a second.
"""

import math
import os
import warnings
from functools import partial

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

import fits_factory
from fits_factory import cards_except, invoke, raw_cards_masked

RA, DEC, PA, SCA, FILTER = 10.0, -44.0, 30.0, 7, "J129"
MJD1 = 61541.97
T = 139.8
GAP = 30.0                                   # seconds from the end of exposure 1 to the start of 2
MJD2 = MJD1 + (T + GAP) / 86400.0

ORIGIN = (1, 768, 1, 768)                    # a 3 x 3 grid of 256-pixel cells at the SCA origin
ELSEWHERE = (2001, 2768, 1001, 1768)         # the same grid elsewhere on the SCA
SMALL = (1001, 1096, 2001, 2096)             # 96 x 96, for the effects
PERS = (1001, 1128, 2001, 2128)              # 128 x 128, for persistence and reproducibility

#: (kind, J129 mag, hlr arcsec, e1, e2) of the grid, one per 256 x 256 cell (row by row)
GRID = [("star", 16.0, 0.3, 0, 0), ("star", 18.0, 0.3, 0, 0), ("star", 20.0, 0.3, 0, 0),
        ("star", 22.0, 0.3, 0, 0), ("galaxy", 18.0, 0.2, 0, 0), ("galaxy", 19.0, 0.5, 0.2, -0.1),
        ("galaxy", 20.0, 0.35, 0, 0), ("galaxy", 21.0, 0.5, 0, 0), ("galaxy", 22.0, 0.3, 0.1, 0.15)]


# -- helpers -------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def optics():
    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    return Optics(Exposure(ra=RA, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD1))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("render")


def write_catalog(path, optics, objects):
    """A truth catalogue of ``objects`` = [(kind, x, y, J, hlr, e1, e2)] at SCA pixels (x, y)."""
    rows = []
    for i, (kind, x, y, mag, hlr, e1, e2) in enumerate(objects, 1):
        ra, dec = optics.wcs.xyToradec(x, y, units="deg")
        rows.append((i, float(ra), float(dec), kind, mag, mag + 0.3, hlr, e1, e2))
    t = Table(rows=rows, names=["id", "ra", "dec", "kind", "mag_J129", "mag_H158", "hlr", "e1", "e2"])
    t["id"] = t["id"].astype(np.int64)
    t.write(str(path), format="fits", overwrite=True)
    return str(path)


def grid_objects(bounds, seed=3):
    rng = np.random.default_rng(seed)
    out = []
    for k, (kind, mag, hlr, e1, e2) in enumerate(GRID):
        i, j = k % 3, k // 3
        x = bounds[0] + 256 * i + 128 + rng.uniform(-0.4, 0.4)
        y = bounds[2] + 256 * j + 128 + rng.uniform(-0.4, 0.4)
        out.append((kind, x, y, mag, hlr, e1, e2))
    return out


def render(out, truth, *extra, bounds=SMALL, mjd=MJD1, ra=RA, seed=1, expect=0):
    args = ["render", truth, "--ra", ra, "--dec", DEC, "--pa", PA, "--mjd", mjd, "--filter", FILTER,
            "--sca", SCA, "--seed", seed, "-o", out, "--overwrite"]
    if bounds is not None:
        args[2:2] = ["--bounds", *bounds]
    result = invoke(*args, *extra)
    assert result.exit_code == expect, (result.exit_code, result.stderr, result.exception)
    return str(out)


def load(path):
    """{extname: (float64 data, header)} of the images, the primary header, the MODEL table and the path."""
    with fits.open(path) as hdul:
        out = {h.name: (np.asarray(h.data, dtype=np.float64), h.header.copy()) for h in hdul[1:] if h.is_image}
        out["PRIMARY"] = (None, hdul[0].header.copy())
        out["MODEL"] = (Table(hdul["MODEL"].data), hdul["MODEL"].header.copy())
    out["path"] = str(path)
    return out


def model_of(f):
    """The detector model a rendered frame carries, read back as --model FRAME.fits reads it."""
    from perscli.detector.model import load_detector_model

    return load_detector_model(f["path"])


def expected_electrons(mag, header):
    import galsim.roman

    return 10.0 ** (-0.4 * (mag - header["ZPT_AB"])) * galsim.roman.collecting_area * header["EXPTIME"]


def astropy_pixels(header, ra, dec):
    """Catalogue positions -> (array x, array y, SCA x, SCA y) with astropy's TAN-SIP reading of the header."""
    from astropy.wcs import WCS, FITSFixedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        w = WCS(header)
    assert w.sip is not None and w.wcs.ctype[0] == "RA---TAN-SIP"
    px, py = w.all_world2pix(ra, dec, 0)                       # 0-based array indices
    # FITS pixel p = px + 1 is the cutout's; SCA pixel = p - LTV
    return px, py, px + 1 - header["LTV1"], py + 1 - header["LTV2"]


def centroid(img, px, py, hw=15):
    ix, iy = int(round(px)), int(round(py))
    win = img[iy - hw:iy + hw + 1, ix - hw:ix + hw + 1]
    yy, xx = np.mgrid[iy - hw:iy + hw + 1, ix - hw:ix + hw + 1]
    return (win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()


def dilate(mask):
    """A mask grown by one pixel in every direction (the reach of IPC)."""
    out = mask.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out |= np.roll(np.roll(mask, dy, 0), dx, 1)
    return out


# -- the grids: flux and WCS ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def grids(work, optics):
    """Two 768 x 768 renders of the 3 x 3 grid: at the SCA origin (noisy chain with gain 2, no
    reciprocity, saturation or nonlinearity: linear) and elsewhere (the default chain)."""
    out = {}
    for name, bounds, extra in [("origin", ORIGIN, ["--set", "reciprocity=off", "--set", "nonlinearity=off",
                                                     "--set", "saturation=off", "--set", "gain.gain=2"]),
                                ("elsewhere", ELSEWHERE, [])]:
        objects = grid_objects(bounds)
        truth = write_catalog(work / f"grid_{name}.fits", optics, objects)
        path = render(work / f"grid_{name}_frame.fits", truth, *extra, bounds=bounds, seed=7)
        out[name] = (objects, Table.read(truth), load(path))
    return out


@pytest.mark.parametrize("where", ["origin", "elsewhere"])
def test_flux_through_the_zeropoint(grids, where):
    objects, cat, f = grids[where]
    ideal = f["IDEAL"][0]
    sci_hdr = f["SCI"][1]
    sky = sci_hdr["SKYRATE"] * sci_hdr["EXPTIME"]
    assert sky > 0
    src = ideal - sky
    fluxes = []
    for k, row in enumerate(cat):
        i, j = k % 3, k // 3
        expect = expected_electrons(row["mag_J129"], sci_hdr)
        fluxes.append(expect)
        cell = src[256 * j:256 * (j + 1), 256 * i:256 * (i + 1)].sum()
        assert cell == pytest.approx(expect, rel=0.01), (row["kind"], row["mag_J129"], row["hlr"])
        # faint stars and compact galaxies: a 64-pixel box holds > 99 %
        if row["mag_J129"] >= 20 and (row["kind"] == "star" or row["hlr"] <= 0.35):
            # array index = SCA pixel - xmin, with xmin = 1 - LTV1
            ax = int(round(objects[k][1])) - 1 + int(sci_hdr["LTV1"])
            ay = int(round(objects[k][2])) - 1 + int(sci_hdr["LTV2"])
            box = src[ay - 32:ay + 32, ax - 32:ax + 32].sum()
            assert 0.99 * expect < box < 1.01 * expect, (row["kind"], row["mag_J129"], box / expect)
    # every stamp lies inside the cutout: the whole frame holds the catalogue's flux exactly
    assert src.sum() == pytest.approx(sum(fluxes), rel=1e-5)


def test_zeropoint_and_sky_are_galsims(grids, optics):
    import galsim.roman

    hdr = grids["origin"][2]["SCI"][1]
    assert hdr["ZPT_AB"] == pytest.approx(galsim.roman.getBandpasses(AB_zeropoint=True)[FILTER].zeropoint,
                                          rel=1e-12)
    assert hdr["SKYRATE"] == pytest.approx(optics.sky_rate(), rel=1e-12)
    # IDEAL far from every object is the sky alone
    ideal = grids["origin"][2]["IDEAL"][0]
    np.testing.assert_allclose(ideal[:5, 380:390], hdr["SKYRATE"] * T, rtol=1e-6)


def test_sci_statistics_against_ideal(grids):
    """SCI * GAIN - IDEAL: mean = dark current x exptime; variance = (sky + dark) x sum(IPC^2)
    + read noise^2 + quantisation (gain^2 / 12) away from the objects."""
    import galsim.roman

    f = grids["origin"][2]
    sci, hdr = f["SCI"]
    ideal = f["IDEAL"][0]
    assert hdr["GAIN"] == 2.0 and hdr["BUNIT"] == "DN"
    assert np.array_equal(sci, np.round(sci))
    resid = (sci * 2.0 - ideal)[1:-1, 1:-1]            # IPC: no charge comes in from beyond the edges
    ideal = ideal[1:-1, 1:-1]
    dark = 0.015 * T
    sky = hdr["SKYRATE"] * T
    k2 = float((galsim.roman.ipc_kernel.array ** 2).sum())
    var = (sky + dark) * k2 + 8.5 ** 2 + 4.0 / 12.0
    assert abs(resid.mean() - dark) < 5 * math.sqrt(var / resid.size) + 0.01
    empty = ~dilate(np.abs(ideal - sky) > 1e-3)
    assert empty.mean() > 0.5
    r = resid[empty]
    assert r.var() == pytest.approx(var, rel=0.03)
    # without the dark current the mean would be 0: the test can tell
    assert abs(resid.mean()) > 1.0


@pytest.mark.parametrize("where", ["origin", "elsewhere"])
def test_wcs_round_trip(grids, optics, where):
    objects, cat, f = grids[where]
    hdr = f["SCI"][1]
    ideal = f["IDEAL"][0]
    src = ideal - hdr["SKYRATE"] * hdr["EXPTIME"]
    xmin, _, ymin, _ = ORIGIN if where == "origin" else ELSEWHERE
    assert (hdr["LTV1"], hdr["LTV2"]) == (1 - xmin, 1 - ymin)
    px, py, sx, sy = astropy_pixels(hdr, np.asarray(cat["ra"]), np.asarray(cat["dec"]))
    gx, gy = optics.positions(np.asarray(cat["ra"]), np.asarray(cat["dec"]))
    truth = np.array([(o[1], o[2]) for o in objects])
    # header WCS (astropy, TAN-SIP, cutout offset) == GalSim's WCS == where the objects were put
    np.testing.assert_allclose(sx, gx, atol=1e-3)
    np.testing.assert_allclose(sy, gy, atol=1e-3)
    np.testing.assert_allclose(np.c_[gx, gy], truth, atol=1e-6)
    # drawn centroids: the object's position plus the PSF's own centroid (GalSim's Roman PSF is not
    # centred: ~(0.02, -0.08) pixel for SCA 7 in J129)
    psf_c = optics.psf_pixels.centroid
    for k, row in enumerate(cat):
        if row["mag_J129"] > 20 or abs(row["e1"]) + abs(row["e2"]) > 0 or row["hlr"] > 0.35:
            continue                                       # bright, round objects only
        cx, cy = centroid(src, px[k], py[k])
        assert abs(cx - (px[k] + psf_c.x)) < 0.05, (row["kind"], row["mag_J129"], cx - px[k])
        assert abs(cy - (py[k] + psf_c.y)) < 0.05, (row["kind"], row["mag_J129"], cy - py[k])
        # and with GalSim's positions (1-indexed SCA pixels -> array indices)
        assert abs(cx - (gx[k] - xmin + psf_c.x)) < 0.05
        assert abs(cy - (gy[k] - ymin + psf_c.y)) < 0.05


def test_wcs_in_every_image_hdu(grids):
    f = grids["elsewhere"][2]
    ref = f["SCI"][1]
    for name in ("IDEAL", "FLUENCE"):
        hdr = f[name][1]
        for key in ("CTYPE1", "CTYPE2", "CRPIX1", "CRPIX2", "CRVAL1", "CRVAL2", "CD1_1", "CD2_2", "A_ORDER",
                    "B_ORDER", "LTV1", "LTV2"):
            assert hdr[key] == ref[key], (name, key)


# -- every effect, on and off ---------------------------------------------------------------------

#: model files of the effect renders: the sky alone, or nothing at all
MODELS = {"sky": "effects:\n  - sky: {level: auto}\n", "none": "effects: []\n"}

#: name -> (model, --set options)
EFFECT_RENDERS = {
    "bare": ("none", []),
    "sky": ("sky", []),
    "sky_level": ("sky", ["sky.level=2.5"]),
    "poisson": ("sky", ["poisson=on"]),
    "reciprocity": ("sky", ["reciprocity.alpha=0.02", "reciprocity.base_flux=2"]),
    "reciprocity_off": ("sky", ["reciprocity.alpha=0.02", "reciprocity=off"]),
    "dark": ("sky", ["dark.current=0.3"]),
    "nonlinearity": ("sky", ["nonlinearity.beta=-2.0e-6"]),
    "ipc": ("sky", ["ipc=on"]),
    "read_noise": ("sky", ["read_noise.sigma=6"]),
    "gain": ("sky", ["gain.gain=2"]),
    "quantize": ("sky", ["read_noise.sigma=6", "quantize=on"]),
    "roman": ("roman", []),
    "roman_no_quantize": ("roman", ["quantize=off"]),
    "roman_no_ipc": ("roman", ["ipc=off"]),
}


@pytest.fixture(scope="module")
def effect_frames(work, optics):
    """Renders of one 96 x 96 cutout (a bright star, a galaxy, a faint star), made on demand."""
    truth = write_catalog(work / "small.fits", optics, [
        ("star", 1040.2, 2050.7, 17.0, 0.3, 0, 0), ("galaxy", 1070.6, 2030.1, 18.0, 0.3, 0.2, 0.0),
        ("star", 1020.4, 2080.3, 21.0, 0.3, 0, 0)])
    models = {}
    for name, text in MODELS.items():
        models[name] = str(work / f"{name}.yaml")
        with open(models[name], "w") as fh:
            fh.write(text)
    models["roman"] = "roman"
    cache = {}

    def get(name):
        if name not in cache:
            model, sets = EFFECT_RENDERS[name]
            extra = ["--model", models[model]]
            for s in sets:
                extra += ["--set", s]
            cache[name] = load(render(work / f"eff_{name}.fits", truth, *extra, seed=3))
        return cache[name]

    get.truth = truth
    return get


def test_no_effects_gives_the_sources(effect_frames):
    f = effect_frames("bare")
    sci, hdr = f["SCI"]
    np.testing.assert_array_equal(sci, f["IDEAL"][0])
    np.testing.assert_array_equal(sci, f["FLUENCE"][0])
    assert hdr["SKYRATE"] == 0.0 and hdr["BUNIT"] == "electron" and hdr["NOBJ"] == 3
    assert sci.max() > 1e5 and sci.min() > -1.0           # the bright star; no sky
    assert len(f["MODEL"][0]) == 0 and model_of(f).effects == []


def test_sky_adds_skyrate_times_exptime(effect_frames, optics):
    bare, sky = effect_frames("bare"), effect_frames("sky")
    hdr = sky["SCI"][1]
    assert hdr["SKYRATE"] == pytest.approx(optics.sky_rate(), rel=1e-12)
    np.testing.assert_allclose(sky["SCI"][0] - bare["SCI"][0], hdr["SKYRATE"] * T, atol=0.02)
    np.testing.assert_array_equal(sky["SCI"][0], sky["IDEAL"][0])
    level = effect_frames("sky_level")
    assert level["SCI"][1]["SKYRATE"] == 2.5
    np.testing.assert_allclose(level["SCI"][0] - bare["SCI"][0], 2.5 * T, atol=0.02)
    assert model_of(level).describe() == [("sky", True, {"level": 2.5})]


def test_poisson_gives_integers_with_variance_equal_to_mean(effect_frames):
    f = effect_frames("poisson")
    sci, ideal = f["SCI"][0], f["IDEAL"][0]
    np.testing.assert_array_equal(ideal, effect_frames("sky")["IDEAL"][0])
    assert np.array_equal(sci, np.round(sci))
    z = (sci - ideal) / np.sqrt(ideal)
    n = sci.size
    assert abs(z.mean()) < 5 / math.sqrt(n)
    assert abs(z.var() - 1) < 5 * math.sqrt(2.0 / n)
    assert model_of(f).describe() == [("sky", True, {"level": "auto"}), ("poisson", True, {})]


def test_reciprocity_formula(effect_frames):
    f = effect_frames("reciprocity")
    x = effect_frames("sky")["SCI"][0]
    expect = x * (1 + 0.02 * np.log10(x / (2.0 * T)))
    np.testing.assert_allclose(f["SCI"][0], expect, rtol=2e-7)
    assert not np.allclose(f["SCI"][0], x, rtol=1e-3)
    # switched off with --set: the parameters stay, the frame is the sky's
    off = effect_frames("reciprocity_off")
    np.testing.assert_array_equal(off["SCI"][0], x)
    rec = model_of(off).get("reciprocity")
    assert not rec.enabled and rec.params == {"alpha": 0.02, "base_flux": 1.0}


def test_dark_adds_current_times_exptime_with_poisson_noise(effect_frames):
    f = effect_frames("dark")
    d = f["SCI"][0] - f["IDEAL"][0]
    mean = 0.3 * T
    np.testing.assert_allclose(d, np.round(d), atol=1e-2)          # whole electrons (float32 of ~200)
    assert abs(d.mean() - mean) < 5 * math.sqrt(mean / d.size)
    assert abs(d.var() / mean - 1) < 5 * math.sqrt(2.0 / d.size)
    np.testing.assert_array_equal(f["FLUENCE"][0], f["SCI"][0])     # dark charge is collected charge


def test_nonlinearity_against_fluence(effect_frames):
    f = effect_frames("nonlinearity")
    x = f["FLUENCE"][0]
    np.testing.assert_array_equal(x, effect_frames("sky")["SCI"][0])
    np.testing.assert_allclose(f["SCI"][0], x - 2e-6 * x * x, rtol=2e-7)
    assert f["SCI"][0].max() < 0.9 * x.max()                       # the bright star is compressed


def test_ipc_spreads_with_the_roman_kernel(effect_frames):
    import galsim
    import galsim.roman

    f = effect_frames("ipc")
    x = f["FLUENCE"][0]
    np.testing.assert_array_equal(x, effect_frames("sky")["SCI"][0])
    im = galsim.Image(x.copy())
    im.applyIPC(galsim.roman.ipc_kernel, edge_treatment="extend")
    # the cutout's edge pixels also receive their neighbours' signal from beyond the cutout (render
    # simulates one more pixel all round): GalSim's cutout-only IPC is the same inside
    inner = (slice(1, -1), slice(1, -1))
    np.testing.assert_allclose(f["SCI"][0][inner], im.array[inner], rtol=1e-6)
    edge = np.ones(x.shape, dtype=bool)
    edge[inner] = False
    assert np.all(f["SCI"][0][edge] > im.array[edge])       # zero padding loses the sky beyond the edge
    # charge is conserved away from the edges, the peak loses ~6 % to its neighbours
    assert f["SCI"][0][inner].sum() == pytest.approx(x[inner].sum(), rel=1e-3)
    j, i = np.unravel_index(np.argmax(x), x.shape)
    assert f["SCI"][0][j, i] < 0.97 * x[j, i]


def test_read_noise_is_gaussian_with_sigma(effect_frames):
    f = effect_frames("read_noise")
    d = f["SCI"][0] - f["IDEAL"][0]
    n = d.size
    assert abs(d.mean()) < 5 * 6 / math.sqrt(n)
    assert abs(d.std() / 6 - 1) < 5 / math.sqrt(2 * n)
    np.testing.assert_array_equal(f["FLUENCE"][0], f["IDEAL"][0])   # read noise is not charge


def test_gain_divides_and_units_become_dn(effect_frames):
    f = effect_frames("gain")
    np.testing.assert_allclose(f["SCI"][0], f["IDEAL"][0] / 2.0, rtol=1e-7)
    assert f["SCI"][1]["BUNIT"] == "DN" and f["SCI"][1]["GAIN"] == 2.0
    assert f["IDEAL"][1]["BUNIT"] == "electron" and f["FLUENCE"][1]["BUNIT"] == "electron"
    sky = effect_frames("sky")["SCI"][1]
    assert sky["BUNIT"] == "electron" and sky["GAIN"] == 1.0


def test_quantize_rounds_the_same_noise(effect_frames):
    q, rn = effect_frames("quantize")["SCI"][0], effect_frames("read_noise")["SCI"][0]
    assert np.array_equal(q, np.round(q))
    assert not np.array_equal(rn, np.round(rn))
    assert np.all(np.abs(q - rn) <= 0.5 + 1e-3)


def test_roman_chain_effects_switched_off_with_set(effect_frames):
    full, noq, noipc = (effect_frames(n)["SCI"][0] for n in ("roman", "roman_no_quantize", "roman_no_ipc"))
    assert np.array_equal(full, np.round(full))
    assert np.all(np.abs(full - noq) <= 0.5 + 1e-3)              # same noise, only the rounding differs
    assert not np.array_equal(noq, np.round(noq))
    # IPC off: the noise changes only through IPC (each effect has its own stream)
    f = effect_frames("roman")
    assert np.abs(full - noipc).max() > 100                      # around the bright star
    assert np.median(np.abs(full - noipc)) < 10
    assert [e.name for e in model_of(f).effects] == ["sky", "poisson", "reciprocity", "dark", "persistence",
                                                     "saturation", "nonlinearity", "ipc", "read_noise", "gain",
                                                     "quantize"]
    assert not model_of(effect_frames("roman_no_ipc")).enabled("ipc")


# -- reproducibility ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pers_truth(work, optics):
    """A bright compact galaxy (J = 16, peak ~2.7e5 e-) and a faint star in the PERS cutout."""
    return write_catalog(work / "pers.fits", optics, [
        ("galaxy", 1064.3, 2064.6, 16.0, 0.1, 0.0, 0.0), ("star", 1100.4, 2030.2, 21.0, 0.3, 0, 0)])


def test_same_seed_same_bytes_other_seed_other_frame_workers_irrelevant(work, pers_truth):
    a = render(work / "rep_a.fits", pers_truth, bounds=PERS, seed=5)
    b = render(work / "rep_b.fits", pers_truth, bounds=PERS, seed=5)
    c = render(work / "rep_c.fits", pers_truth, bounds=PERS, seed=6)
    w = render(work / "rep_w.fits", pers_truth, "--workers", "2", bounds=PERS, seed=5)
    assert raw_cards_masked(a) == raw_cards_masked(b) == raw_cards_masked(w)
    assert cards_except(a) == cards_except(b)
    fa, fc = load(a), load(c)
    for name in ("SCI", "IDEAL", "FLUENCE"):
        np.testing.assert_array_equal(fa[name][0], load(b)[name][0])
    assert np.mean(fa["SCI"][0] != fc["SCI"][0]) > 0.9
    np.testing.assert_array_equal(fa["IDEAL"][0], fc["IDEAL"][0])        # the noise-free frame is the same
    assert fc["PRIMARY"][1]["SEED"] == 6 and fa["SCI"][1]["SEED"] == 5


# -- persistence pairs ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pairs(work, pers_truth):
    """Exposure 1 (full chain, and bare: sources only) and exposure 2, 30 s later, dithered by ~3",
    with and without persistence."""
    p = {}
    p["e1"] = render(work / "e1.fits", pers_truth, bounds=PERS, seed=1)
    sky0 = work / "bare.yaml"
    sky0.write_text("effects: []\n")
    p["e1_bare"] = render(work / "e1_bare.fits", pers_truth, "--model", sky0, bounds=PERS, seed=1)
    ra2 = RA + 0.0012
    every = ["--persistence-source", "all"]         # the earlier exposure's FLUENCE persists (default: drawn)
    simple = ["--set", "nonlinearity=off", "--set", "ipc=off", "--set", "quantize=off", "--set", "saturation=off",
              "--set", "gain.gain=2"]
    p["with"] = render(work / "e2_with.fits", pers_truth, "--previous", p["e1"], *every, *simple,
                       bounds=PERS, mjd=MJD2, ra=ra2, seed=2)
    p["off"] = render(work / "e2_off.fits", pers_truth, "--previous", p["e1"], *every, "--set", "persistence=off",
                      *simple, bounds=PERS, mjd=MJD2, ra=ra2, seed=2)
    p["none"] = render(work / "e2_none.fits", pers_truth, *simple, bounds=PERS, mjd=MJD2, ra=ra2, seed=2)
    p["drawn"] = render(work / "e2_drawn.fits", pers_truth, "--previous", p["e1"], *simple,      # the default
                        bounds=PERS, mjd=MJD2, ra=ra2, seed=2)
    p["full_with"] = render(work / "e2_full_with.fits", pers_truth, "--previous", p["e1_bare"], *every,
                            bounds=PERS, mjd=MJD2, ra=ra2, seed=2)
    p["full_none"] = render(work / "e2_full_none.fits", pers_truth, bounds=PERS, mjd=MJD2, ra=ra2, seed=2)
    return p


def test_persistence_difference_is_persist(pairs):
    w, off, none = load(pairs["with"]), load(pairs["off"]), load(pairs["none"])
    assert "PERSIST" in w and "PERSIST" not in off and "PERSIST" not in none
    np.testing.assert_array_equal(off["SCI"][0], none["SCI"][0])       # --previous ignored when off
    pers = w["PERSIST"][0]
    assert pers.max() > 5.0 and pers.min() >= 0
    assert w["PERSIST"][1]["BUNIT"] == "electron"
    sw, so = w["SCI"][0], off["SCI"][0]
    tol = np.spacing(np.abs(sw).astype(np.float32)) + np.spacing(np.abs(so).astype(np.float32)) \
        + np.spacing(pers.astype(np.float32))
    assert np.all(np.abs((sw - so) - pers / 2.0) <= tol)
    np.testing.assert_allclose(w["FLUENCE"][0] - off["FLUENCE"][0], pers, atol=0.05)
    np.testing.assert_array_equal(w["IDEAL"][0], off["IDEAL"][0])


def test_persistence_with_the_full_chain_changes_only_persistent_pixels(pairs):
    from perscli.detector.effects import apply_ipc, roman_ipc_kernel

    w, n = load(pairs["full_with"]), load(pairs["full_none"])
    pers = w["PERSIST"][0]
    touched = pers != 0
    assert 0.05 < touched.mean() < 0.6                 # the earlier exposure's stamps only (no sky in it)
    reach = dilate(touched)
    sw, sn = w["SCI"][0], n["SCI"][0]
    np.testing.assert_array_equal(sw[~reach], sn[~reach])               # identical noise elsewhere
    assert np.count_nonzero(sw[reach] != sn[reach]) > 50
    fw, fn = w["FLUENCE"][0], n["FLUENCE"][0]
    np.testing.assert_allclose(fw - fn, pers, atol=0.05)
    # the difference is the persistence through nonlinearity and IPC, then rounded
    beta = -6.0e-7
    expect = apply_ipc((fw + beta * fw ** 2) - (fn + beta * fn ** 2), roman_ipc_kernel())
    assert np.all(np.abs((sw - sn) - expect) <= 1.0 + 0.05)


def test_persist_matches_apply_persistence_predict(pairs, work):
    from perscli.detector.persistence import PersistenceModel, persistence_charge
    from perscli.detector.settings import PRESETS
    from perscli.io.frames import SECONDS_PER_DAY, open_frame

    w = load(pairs["with"])
    pers, hdr = w["PERSIST"][0], w["SCI"][1]
    # the command line, on the rendered exposure 2 (DN, gain 2)
    out = work / "predict.fits"
    result = invoke("apply-persistence", pairs["with"], pairs["e1"], "--mode", "predict", "-o", out, "--overwrite")
    assert result.exit_code == 0, result.stderr
    with fits.open(out) as hdul:
        pred = np.asarray(hdul["SCI"].data, dtype=np.float64)
    np.testing.assert_allclose(pred * hdr["GAIN"], pers, rtol=1e-6, atol=1e-6)
    # the library on arrays, from e1's FLUENCE and e2's EXPSTART/EXPEND
    with open_frame(pairs["e1"]) as prev:
        fluence, scale = prev.fluence()
        end = prev.end
    lib = persistence_charge([fluence * scale], [end * SECONDS_PER_DAY], hdr["EXPSTART"] * SECONDS_PER_DAY,
                             (hdr["EXPEND"] - hdr["EXPSTART"]) * SECONDS_PER_DAY,
                             PersistenceModel(name="typical", **PRESETS["typical"]))[0]
    np.testing.assert_allclose(pers, lib.astype(np.float32), rtol=1e-6, atol=1e-7)
    # and by hand: F(fluence) times the integral of (t / 1000 s)^-1 over exposure 2
    e1 = load(pairs["e1"])
    gap = (hdr["EXPSTART"] - e1["SCI"][1]["EXPEND"]) * 86400.0
    assert gap == pytest.approx(GAP, abs=1e-3)
    model = PersistenceModel(name="typical", **PRESETS["typical"])
    by_hand = model.F(e1["FLUENCE"][0]) * 1000.0 * math.log((gap + T) / gap)
    np.testing.assert_allclose(pers, by_hand, rtol=1e-5, atol=1e-6)
    # the brightest pixel of exposure 1 leaves the most persistence
    assert np.argmax(pers) == np.argmax(e1["FLUENCE"][0])


def test_persistence_provenance(pairs):
    w = load(pairs["with"])
    prim = w["PRIMARY"][1]
    assert prim["PRV01"] == "e1.fits"
    with fits.open(pairs["e1"]) as hdul:
        assert prim["PRV01DS"] == hdul["FLUENCE"].header["DATASUM"]
    assert prim["PSP01DT"] == pytest.approx(GAP, abs=1e-3)
    assert "previous=1" in " ".join(prim["HISTORY"])
    assert "PRV01" not in load(pairs["off"])["PRIMARY"][1]
    assert prim["PS_SRC"] == "all"
    # the default source: the light drawn on the earlier exposure (its DRAWN) persists
    drawn = load(pairs["drawn"])["PRIMARY"][1]
    assert drawn["PS_SRC"] == "drawn" and drawn["PRV01"] == "e1.fits"
    with fits.open(pairs["e1"]) as hdul:
        assert drawn["PRV01DS"] == hdul["DRAWN"].header["DATASUM"] != hdul["FLUENCE"].header["DATASUM"]


# -- output structure -----------------------------------------------------------------------------

def test_hdus_and_headers(pairs):
    # the default HDUs: DRAWN among them (the default persistence source is the light drawn)
    for name, ext in (("with", ["PRIMARY", "SCI", "IDEAL", "FLUENCE", "DRAWN", "PERSIST", "MODEL"]),
                      ("none", ["PRIMARY", "SCI", "IDEAL", "FLUENCE", "DRAWN", "MODEL"])):
        with fits.open(pairs[name]) as hdul:
            assert [h.name for h in hdul] == ext
            assert all(h.data.dtype == np.dtype(">f4") and h.data.shape == (128, 128) for h in hdul[1:-1])
            assert hdul["MODEL"].columns.names == ["EFFECT", "ENABLED", "PARAM", "VALUE", "UNIT"]
            for h in hdul[1:-1]:
                hdr = h.header
                for key in ("EXPSTART", "EXPEND", "EXPTIME", "SCA", "FILTER", "GAIN", "BUNIT", "CTYPE1",
                            "CRVAL1", "CD1_1", "LTV1", "LTV2", "DATE-OBS"):
                    assert key in hdr, (h.name, key)
                assert hdr["EXPSTART"] == pytest.approx(MJD2, abs=1e-9)
                assert (hdr["EXPEND"] - hdr["EXPSTART"]) * 86400 == pytest.approx(T, abs=1e-3)
                assert hdr["EXPTIME"] == T and hdr["SCA"] == SCA and hdr["FILTER"] == FILTER
                assert (hdr["LTV1"], hdr["LTV2"]) == (1 - PERS[0], 1 - PERS[2])
            sci = hdul["SCI"].header
            assert sci["BUNIT"] == "DN" and sci["GAIN"] == 2.0 and sci["NOBJ"] == 2
            assert sci["EXPID"] == -1 and sci["SEED"] == 2


def test_no_duplicate_keywords(pairs):
    with fits.open(pairs["none"]) as hdul:
        for h in hdul:
            keys = [c.keyword for c in h.header.cards if c.keyword not in ("HISTORY", "COMMENT", "")]
            dupes = sorted({k for k in keys if keys.count(k) > 1})
            assert dupes == [], (h.name, dupes)
        assert hdul["SCI"].header["INSTRUME"] == "WFI"


def test_checksums_verify(pairs):
    for name in ("with", "e1"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with fits.open(pairs[name], checksum=True) as hdul:
                for h in hdul:
                    assert "CHECKSUM" in h.header and "DATASUM" in h.header
                    h.data                                          # noqa: B018 (read, verified)
    # and a changed byte is caught
    raw = bytearray(open(pairs["none"], "rb").read())
    with fits.open(pairs["none"]) as hdul:
        loc = hdul["IDEAL"].fileinfo()["datLoc"]
    raw[loc + 1001] ^= 0x10
    bad = pairs["none"] + ".bad.fits"
    with open(bad, "wb") as fh:
        fh.write(raw)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with fits.open(bad, checksum=True) as hdul:
            [h.data for h in hdul]
    assert any("checksum" in str(w.message).lower() or "datasum" in str(w.message).lower() for w in caught)
    os.unlink(bad)


def test_provenance(pairs, pers_truth):
    prim = load(pairs["full_none"])["PRIMARY"][1]
    assert prim["CREATOR"].startswith("perscli ")
    assert prim["TRUTH"] == "pers.fits"
    with fits.open(pers_truth, checksum=True) as hdul:
        table = [h for h in hdul if isinstance(h, fits.BinTableHDU)][0]
        assert prim["TRUTHDS"] == str(table._calculate_datasum())
    assert prim["SEED"] == 2 and prim["DETMODEL"] == "roman" and prim["DETNEFF"] == 11
    assert prim["FILTER"] == FILTER and prim["SCA"] == SCA
    from perscli.detector.model import load_detector_model

    assert model_of(load(pairs["full_none"])).describe() == load_detector_model("roman").describe()
    assert "EFF01" not in prim                                   # the model is in the MODEL table
    assert any("render sca=7 filter=J129" in h for h in prim["HISTORY"])
    assert "DATE" in prim


def test_pointings_row_gives_the_same_exposure(work, pers_truth, pairs):
    table = Table({"expid": np.array([11, 12], dtype=np.int64), "mjd": [MJD1, MJD2], "exptime": [T, T],
                   "ra": [RA, RA + 0.0012], "dec": [DEC, DEC], "pa": [PA, PA], "filter": [FILTER, FILTER],
                   "sca": np.array([SCA, SCA], dtype=np.int32)})
    ptg = str(work / "pointings.fits")
    table.write(ptg, format="fits", overwrite=True)
    out = str(work / "from_pointings.fits")
    result = invoke("render", pers_truth, "--pointings", ptg, "--row", 1, "--bounds", *PERS, "--seed", 2,
                    "-o", out, "--overwrite")
    assert result.exit_code == 0, result.stderr
    a, b = load(out), load(pairs["full_none"])
    np.testing.assert_array_equal(a["SCI"][0], b["SCI"][0])
    assert a["SCI"][1]["EXPID"] == 12
    assert a["SCI"][1]["EXPSTART"] == b["SCI"][1]["EXPSTART"]


# -- errors ---------------------------------------------------------------------------------------

BASE = ["--ra", RA, "--dec", DEC, "--pa", PA, "--mjd", MJD1, "--filter", FILTER, "--sca", SCA,
        "--bounds", *SMALL, "--seed", 1]


#: ``expect_error(tmp_path, ARGS, *needles, code=1)``: ``perscli render ARGS -o OUT`` fails in one line holding
#: every needle, and writes nothing (:func:`fits_factory.expect_error`)
expect_error = partial(fits_factory.expect_error, command="render")


@pytest.fixture
def truth_file(tmp_path, optics):
    return write_catalog(tmp_path / "truth.fits", optics, [("star", 1040.2, 2050.7, 19.0, 0.3, 0, 0)])


@pytest.mark.parametrize("column", ["hlr", "mag_J129", "kind"])
def test_error_truth_missing_column(tmp_path, truth_file, column):
    t = Table.read(truth_file)
    t.remove_column(column)
    t.write(truth_file, overwrite=True)
    err = expect_error(tmp_path, [truth_file, *BASE], column, "column")
    assert "truth" in err


def test_error_truth_missing_file(tmp_path):
    expect_error(tmp_path, [tmp_path / "nope.fits", *BASE], "no such file")


def test_error_unknown_filter(tmp_path, truth_file):
    args = [truth_file, *BASE]
    args[args.index("--filter") + 1] = "J130"
    expect_error(tmp_path, args, "unknown filter", "J130")


def test_error_row_past_the_end(tmp_path, truth_file):
    table = Table({"expid": np.array([0], dtype=np.int64), "mjd": [MJD1], "exptime": [T], "ra": [RA],
                   "dec": [DEC], "pa": [PA], "filter": [FILTER], "sca": np.array([SCA], dtype=np.int32)})
    ptg = str(tmp_path / "p.fits")
    table.write(ptg, format="fits")
    expect_error(tmp_path, [truth_file, "--pointings", ptg, "--row", 3, "--seed", 1], "--row 3", "past the end")


def test_error_previous_of_another_shape(tmp_path, truth_file):
    prev = tmp_path / "prev.fits"
    render(prev, truth_file, bounds=(1001, 1064, 2001, 2064))                 # 64 x 64
    args = [truth_file, *BASE, "--previous", prev]
    args[args.index("--mjd") + 1] = MJD2
    expect_error(tmp_path, args, "shape")


def test_error_previous_not_earlier(tmp_path, truth_file):
    prev = tmp_path / "prev.fits"
    render(prev, truth_file, mjd=MJD2)
    expect_error(tmp_path, [truth_file, *BASE, "--previous", prev], "not an earlier exposure")


@pytest.mark.parametrize("setting, needle", [
    ("blur=off", "unknown effect 'blur'"),
    ("read_noise.rms=3", "unknown parameter(s) rms"),
    ("gain.gain=0", "must be positive"),
    ("dark=sometimes", "dark=on or dark=off"),
])
def test_error_bad_set(tmp_path, truth_file, setting, needle):
    expect_error(tmp_path, [truth_file, *BASE, "--set", setting], needle)


@pytest.mark.parametrize("text, needle", [
    ("effects:\n  - sky\n  - smear: {}\n", "unknown effect 'smear'"),
    ("effects:\n  - gain: {gain: 2}\n  - read_noise: {sigma: 3}\n", "physical order"),
    ("effects: [\n", "not valid YAML"),
])
def test_error_bad_model(tmp_path, truth_file, text, needle):
    model = tmp_path / "model.yaml"
    model.write_text(text)
    expect_error(tmp_path, [truth_file, *BASE, "--model", model], needle)


def test_usage_error_missing_seed(tmp_path, truth_file):
    args = [truth_file, *BASE]
    i = args.index("--seed")
    del args[i:i + 2]
    expect_error(tmp_path, args, "--seed", code=2)


def test_usage_error_no_pointing(tmp_path, truth_file):
    expect_error(tmp_path, [truth_file, "--sca", SCA, "--seed", 1], "--pointings", code=2)
    expect_error(tmp_path, [truth_file, "--ra", RA, "--dec", DEC, "--sca", SCA, "--seed", 1],
                 "--pa", "--mjd", "--filter", code=2)


@pytest.mark.parametrize("sca", [0, 19])
def test_usage_error_sca_out_of_range(tmp_path, truth_file, sca):
    args = [truth_file, *BASE]
    args[args.index("--sca") + 1] = sca
    expect_error(tmp_path, args, "--sca", code=2)


def test_error_previous_of_another_sca(tmp_path, truth_file):
    prev = tmp_path / "prev.fits"
    render(prev, truth_file)
    with fits.open(prev, mode="update") as hdul:          # the same frame, said to be of SCA 8
        for h in hdul:
            if "SCA" in h.header:
                h.header["SCA"] = 8
    args = [truth_file, *BASE, "--previous", prev]
    args[args.index("--mjd") + 1] = MJD2
    expect_error(tmp_path, args, "SCA")


@pytest.mark.parametrize("bounds", [(64, 1, 1, 64), (1, 4089, 1, 64), (0, 10, 1, 10)])
def test_error_bad_bounds(tmp_path, truth_file, bounds):
    args = [truth_file, *BASE]
    i = args.index("--bounds")
    args[i + 1:i + 5] = bounds
    expect_error(tmp_path, args, "--bounds", "min <= max")


def test_exposure_from_a_row_of_the_real_schedule(shared_data, tmp_path):
    """render takes a row of the public Roman schedule directly (date, exptime, ra, dec, pa, filter)."""
    from astropy.io import fits as _fits
    from click.testing import CliRunner as _Runner

    from perscli.cli.main import cli as _cli

    schedule = shared_data / "roman" / "Roman_WAS_obseq_11_1_23.fits"
    row = _fits.getdata(schedule)[4183]
    truth = tmp_path / "t.fits"
    r = _Runner().invoke(_cli, ["catalog", "--ra", str(row["ra"]), "--dec", str(row["dec"]), "--size", "2",
                                "--seed", "5", "-o", str(truth)])
    assert r.exit_code == 0, r.output
    out = tmp_path / "e.fits"
    r = _Runner().invoke(_cli, ["render", str(truth), "--pointings", str(schedule), "--row", "4183", "--sca", "3",
                                "--bounds", "1", "64", "1", "64", "--seed", "1", "-o", str(out)])
    assert r.exit_code == 0, r.output
    hdr = _fits.getheader(out, "SCI")
    assert hdr["EXPSTART"] == row["date"] and hdr["EXPTIME"] == row["exptime"]
    assert hdr["FILTER"] == row["filter"].strip() and hdr["EXPID"] == 4183 and hdr["PA_PNT"] == row["pa"]
