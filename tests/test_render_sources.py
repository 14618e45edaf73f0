"""perscli render: what persists (--persistence-source drawn|stars|all|ELECTRONS), the fluence cap,
the light drawn (DRAWN) and the stars' (STARFLU), the choice of HDUs (--hdus), compressed history frames,
frames without objects, and the Exposure of a schedule row.

One earlier exposure (the history, rendered once with FLUENCE, DRAWN and STARFLU) and a later one 30 s after it,
dithered by ~3", rendered with and without persistence from it under each source.  Every PERSIST is
checked against the paper's law by hand: F(x) times the integral of (t / 1000 s)^-1 over the later
exposure, 1000 ln((gap + T) / gap).
"""

import math
import os

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from fits_factory import invoke, listing, raw_cards_masked

RA, DEC, PA, SCA, FILTER = 10.0, -44.0, 30.0, 7, "J129"
MJD1 = 61541.97
T = 139.8
GAP = 30.0
MJD2 = MJD1 + (T + GAP) / 86400.0
RA2 = RA + 0.0012
BOUNDS = (1001, 1128, 2001, 2128)              # 128 x 128
WELL = 1.0e5

#: (kind, x, y, J129, hlr): a star that saturates, a bright compact galaxy (~2.7e5 e- at its peak: its
#: own light would persist under 'all' but not under 'stars'), a faint star and a measurable galaxy
OBJECTS = [("star", 1040.3, 2050.6, 13.5, 0.0), ("galaxy", 1095.2, 2090.7, 16.0, 0.1),
           ("star", 1020.5, 2105.5, 19.0, 0.0), ("galaxy", 1090.4, 2030.2, 20.0, 0.3)]


@pytest.fixture(scope="module")
def optics():
    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    return Optics(Exposure(ra=RA, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD1))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("sources")


def write_catalog(path, optics, objects):
    rows = []
    for i, (kind, x, y, mag, hlr) in enumerate(objects, 1):
        ra, dec = optics.wcs.xyToradec(x, y, units="deg")
        rows.append((i, float(ra), float(dec), kind, mag, mag + 0.3, hlr, 0.1 if kind == "galaxy" else 0.0, 0.0))
    t = Table(rows=rows, names=["id", "ra", "dec", "kind", "mag_J129", "mag_H158", "hlr", "e1", "e2"])
    t["id"] = t["id"].astype(np.int64)
    t.write(str(path), format="fits", overwrite=True)
    return str(path)


def render(out, truth, *extra, mjd=MJD1, ra=RA, seed=1, bounds=BOUNDS, expect=0):
    args = ["render", truth, "--ra", ra, "--dec", DEC, "--pa", PA, "--mjd", mjd, "--filter", FILTER,
            "--sca", SCA, "--seed", seed, "-o", out, "--overwrite"]
    if bounds is not None:
        args[2:2] = ["--bounds", *bounds]
    result = invoke(*args, *extra)
    assert result.exit_code == expect, (result.exit_code, result.stderr, result.exception)
    return str(out) if expect == 0 else result


def later(work, truth, name, *extra, seed=2, expect=0):
    return render(work / name, truth, *extra, mjd=MJD2, ra=RA2, seed=seed, expect=expect)


def images(path):
    """{extname: float64 data} of the images, and 'PRIMARY'/'headers' for the headers."""
    with fits.open(path) as hdul:
        out = {h.name: np.asarray(h.data, dtype=np.float64) for h in hdul[1:] if h.is_image}
        out["headers"] = {h.name: h.header.copy() for h in hdul}
        out["names"] = [h.name for h in hdul]
    return out


def law(x):
    """The paper's persistence in the later exposure from a fluence x of the earlier one, by hand."""
    from perscli.detector.persistence import PersistenceModel
    from perscli.detector.settings import PRESETS

    model = PersistenceModel(name="typical", **PRESETS["typical"])
    return model.F(np.asarray(x, dtype=np.float64)) * 1000.0 * math.log((GAP + T) / GAP)


def dilate(mask):
    out = mask.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out |= np.roll(np.roll(mask, dy, 0), dx, 1)
    return out


@pytest.fixture(scope="module")
def truth(work, optics):
    return write_catalog(work / "truth.fits", optics, OBJECTS)


@pytest.fixture(scope="module")
def hist(work, truth):
    """The earlier exposure rendered once with everything (full chain), once without saturation, once
    tile-compressed; and the later exposure without persistence (the reference)."""
    every = "SCI,IDEAL,FLUENCE,DRAWN,STARFLU,MODEL"
    h = {}
    h["full"] = render(work / "h_full.fits", truth, "--hdus", every)
    h["nosat"] = render(work / "h_nosat.fits", truth, "--set", "saturation=off", "--hdus", "FLUENCE,DRAWN,STARFLU")
    h["gz"] = render(work / "h_gz.fits", truth, "--hdus", every, "--compress", "gzip")
    h["ref"] = later(work, truth, "ref.fits")
    return h


# -- the stars' fluence --------------------------------------------------------------------------

def test_starflu_is_the_light_of_the_stars_alone(work, truth, optics, hist):
    h = images(hist["full"])
    assert h["names"] == ["PRIMARY", "SCI", "IDEAL", "FLUENCE", "DRAWN", "STARFLU", "MODEL"]
    stars_only = write_catalog(work / "stars_only.fits", optics, [o for o in OBJECTS if o[0] == "star"])
    bare = work / "bare.yaml"
    bare.write_text("effects: []\n")
    alone = images(render(work / "stars_alone.fits", stars_only, "--model", bare, "--hdus", "IDEAL"))
    np.testing.assert_allclose(h["STARFLU"], alone["IDEAL"], rtol=1e-6, atol=1e-6)
    # noise-free and not clipped at the well: the saturating star's core is far above it
    assert h["STARFLU"].max() > 3 * WELL and h["FLUENCE"].max() <= WELL
    # the bright galaxy is in FLUENCE, not in STARFLU
    gx, gy = OBJECTS[1][1] - BOUNDS[0], OBJECTS[1][2] - BOUNDS[2]
    core = (slice(int(gy) - 1, int(gy) + 2), slice(int(gx) - 1, int(gx) + 2))
    assert h["FLUENCE"][core].max() > 5e4 and h["STARFLU"][core].max() < 100
    hdr = h["headers"]["STARFLU"]
    assert hdr["BUNIT"] == "electron" and hdr["EXPSTART"] == MJD1 and hdr["SCA"] == SCA
    assert "stars" in hdr["CONTENT"] and h["headers"]["FLUENCE"]["SATWELL"] == WELL


def test_drawn_is_the_light_of_every_object(hist):
    h = images(hist["full"])
    # every object's expected electrons: IDEAL without its sky, not clipped at the well
    sky = h["headers"]["PRIMARY"]["SKYRATE"] * T
    np.testing.assert_allclose(h["DRAWN"], h["IDEAL"] - sky, rtol=1e-6, atol=1e-3)
    assert h["DRAWN"].max() > 3 * WELL and h["DRAWN"].min() >= 0
    gx, gy = OBJECTS[1][1] - BOUNDS[0], OBJECTS[1][2] - BOUNDS[2]
    core = (slice(int(gy) - 1, int(gy) + 2), slice(int(gx) - 1, int(gx) + 2))
    assert h["DRAWN"][core].max() > 5e4 > 100 > h["STARFLU"][core].max()
    assert "every object" in h["headers"]["DRAWN"]["CONTENT"]


def test_drawn_by_default_and_workers_give_the_same_bytes(work, truth):
    a = render(work / "w1.fits", truth, "--hdus", "SCI,FLUENCE,DRAWN,STARFLU")
    b = render(work / "w2.fits", truth, "--hdus", "SCI,FLUENCE,DRAWN,STARFLU", "--workers", 2)
    c = render(work / "w3.fits", truth, "--hdus", "SCI,FLUENCE,DRAWN,STARFLU")
    assert raw_cards_masked(a) == raw_cards_masked(b) == raw_cards_masked(c)
    # the default persistence source is the light drawn: a frame made with the default HDUs is a history
    names = images(render(work / "w4.fits", truth))["names"]
    assert "DRAWN" in names and "STARFLU" not in names
    assert "DRAWN" not in images(render(work / "w5.fits", truth, "--hdus", "SCI,FLUENCE"))["names"]


# -- what persists --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def persisted(work, truth, hist):
    p = {}
    p["all"] = later(work, truth, "all.fits", "--previous", hist["full"], "--persistence-source", "all")
    p["drawn"] = later(work, truth, "drawn.fits", "--previous", hist["full"])
    p["drawn_flag"] = later(work, truth, "drawn_flag.fits", "--previous", hist["full"], "--persistence-source",
                            "drawn")
    p["stars"] = later(work, truth, "stars.fits", "--previous", hist["full"], "--persistence-source", "stars")
    p["thr"] = later(work, truth, "thr.fits", "--previous", hist["full"], "--persistence-source", "5e4")
    p["stars_set"] = later(work, truth, "stars_set.fits", "--previous", hist["full"],
                           "--set", "persistence.source=stars")
    return p


def test_source_all_is_every_photon(hist, persisted):
    h, a = images(hist["full"]), images(persisted["all"])
    np.testing.assert_allclose(a["PERSIST"], law(h["FLUENCE"]), rtol=1e-5, atol=1e-6)
    assert a["PERSIST"].min() > 0                       # the earlier exposure's sky persists everywhere
    # 'drawn' is the default (render and study alike)
    assert raw_cards_masked(persisted["drawn"]) == raw_cards_masked(persisted["drawn_flag"])


def test_source_drawn_is_the_light_of_every_object_uncapped(hist, persisted):
    h, d = images(hist["full"]), images(persisted["drawn"])
    np.testing.assert_allclose(d["PERSIST"], law(h["DRAWN"]), rtol=1e-5, atol=1e-6)
    a = images(persisted["all"])
    # no sky persists (the drawn light has none): far from the objects, nothing; the galaxy's light does
    gx, gy = OBJECTS[1][1] - BOUNDS[0], OBJECTS[1][2] - BOUNDS[2]
    core = (slice(int(gy) - 1, int(gy) + 2), slice(int(gx) - 1, int(gx) + 2))
    sky = law(h["headers"]["PRIMARY"]["SKYRATE"] * T)
    assert d["PERSIST"][core].max() > 10 and np.median(d["PERSIST"]) < np.median(a["PERSIST"]) - 0.5 * sky
    # the saturated core of the star leaves more than the well would (no cap by default, as GalSim)
    sx, sy = int(round(OBJECTS[0][1] - BOUNDS[0])), int(round(OBJECTS[0][2] - BOUNDS[2]))
    assert d["PERSIST"][sy, sx] > a["PERSIST"][sy, sx] * (1 + 1e-4)


def test_source_stars_is_the_light_of_stars(hist, persisted):
    h, s = images(hist["full"]), images(persisted["stars"])
    np.testing.assert_allclose(s["PERSIST"], law(h["STARFLU"]), rtol=1e-5, atol=1e-6)
    a = images(persisted["all"])
    # no sky and no galaxy light persists: the bright galaxy's core leaves next to nothing
    gx, gy = OBJECTS[1][1] - BOUNDS[0], OBJECTS[1][2] - BOUNDS[2]
    core = (slice(int(gy) - 1, int(gy) + 2), slice(int(gx) - 1, int(gx) + 2))
    assert a["PERSIST"][core].max() > 10 and s["PERSIST"][core].max() < 0.5
    # the star's uncapped core leaves more than the collected (saturated) charge of source all
    sx, sy = int(round(OBJECTS[0][1] - BOUNDS[0])), int(round(OBJECTS[0][2] - BOUNDS[2]))
    assert s["PERSIST"][sy, sx] > a["PERSIST"][sy, sx]
    # --set persistence.source=stars is the same model
    np.testing.assert_array_equal(images(persisted["stars_set"])["SCI"], s["SCI"])


def test_source_threshold_keeps_only_pixels_above_it(hist, persisted):
    h, t = images(hist["full"]), images(persisted["thr"])
    above = h["FLUENCE"] > 5e4
    assert 0 < above.sum() < 200
    np.testing.assert_allclose(t["PERSIST"], law(np.where(above, h["FLUENCE"], 0.0)), rtol=1e-5, atol=1e-6)
    assert np.all(t["PERSIST"][~above] == 0)


@pytest.mark.parametrize("source", ["all", "drawn", "stars", "thr"])
def test_paired_frames_share_their_noise(hist, persisted, source):
    """With and without persistence, same seed: SCI differs only by the persistence through nonlinearity
    and IPC, rounded; FLUENCE by PERSIST; IDEAL not at all."""
    from perscli.detector.effects import apply_ipc, roman_ipc_kernel

    w, n = images(persisted[source]), images(hist["ref"])
    pers = w["PERSIST"]
    reach = dilate(pers > 0)
    np.testing.assert_array_equal(w["SCI"][~reach], n["SCI"][~reach])
    np.testing.assert_array_equal(w["IDEAL"], n["IDEAL"])
    fw, fn = w["FLUENCE"], n["FLUENCE"]
    touched = pers > 0
    np.testing.assert_allclose((fw - fn)[touched & (fw < WELL)], pers[touched & (fw < WELL)], atol=0.05)
    beta = -6.0e-7
    expect = apply_ipc((fw + beta * fw ** 2) - (fn + beta * fn ** 2), roman_ipc_kernel())
    assert np.all(np.abs((w["SCI"] - n["SCI"]) - expect) <= 1.0 + 0.05)
    if source == "thr":
        assert reach.mean() < 0.05 and np.count_nonzero(w["SCI"] != n["SCI"]) > 10


def test_source_is_recorded(persisted):
    for name, src, thr in (("all", "all", None), ("drawn", "drawn", None), ("stars", "stars", None),
                           ("thr", "threshold", 5e4)):
        f = images(persisted[name])
        for ext in ("PRIMARY", "PERSIST"):
            hdr = f["headers"][ext]
            assert hdr["PS_SRC"] == src and hdr["PS_CAP"] == "none"
            assert hdr.get("PS_THR") == thr
        with fits.open(persisted[name]) as hdul:
            rows = {(r["EFFECT"], r["PARAM"]): r["VALUE"] for r in hdul["MODEL"].data}
        assert rows[("persistence", "source")] == {"all": '"all"', "drawn": '"drawn"', "stars": '"stars"',
                                                   "thr": "50000.0"}[name]
        assert rows[("persistence", "fluence_cap")] == '"none"'
    assert "PS_SRC" not in images(persisted["all"])["headers"]["SCI"]


def test_model_of_a_frame_reproduces_its_source(work, truth, hist, persisted):
    again = later(work, truth, "again.fits", "--previous", hist["full"], "--model", persisted["thr"])
    np.testing.assert_array_equal(images(again)["PERSIST"], images(persisted["thr"])["PERSIST"])


def test_library_render_file_with_a_source(work, truth, hist, persisted):
    from perscli.detector.model import load_detector_model
    from perscli.render.exposure import Exposure
    from perscli.render.run import render_file
    from perscli.render.settings import RenderOptions

    model = load_detector_model("roman")
    before = model.describe()
    exposure = Exposure(ra=RA2, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD2, bounds=BOUNDS)
    out = str(work / "lib_stars.fits")
    summary = render_file(truth, exposure, out, RenderOptions(persistence_source="stars", hdus=("PERSIST", "SCI")),
                          model=model, seed=2, previous=[hist["full"]], overwrite=True)
    assert model.describe() == before                                  # the caller's model is not changed
    assert summary["hdus"] == ("SCI", "PERSIST") and summary["persistence_source"] == "stars"
    assert summary["fluence_cap"] is None and summary["objects"] == 4
    np.testing.assert_array_equal(images(out)["PERSIST"], images(persisted["stars"])["PERSIST"])
    thr = render_file(truth, exposure, str(work / "lib_thr.fits"), RenderOptions(persistence_source=5e4,
                      hdus="SCI,PERSIST"), model=model, seed=2, previous=[hist["full"]], overwrite=True)
    assert thr["persistence_source"] == "threshold" and thr["persistence_threshold"] == 5e4


@pytest.mark.parametrize("value, needle", [("-5", "persistence.source"), ("planets", "persistence.source")])
def test_bad_source_is_one_line(work, truth, hist, value, needle):
    result = later(work, truth, "bad.fits", "--previous", hist["full"], "--persistence-source", value, expect=1)
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ") and needle in lines[0]
    assert not (work / "bad.fits").exists()


# -- the fluence cap at the full well -----------------------------------------------------------------

def test_fluence_above_the_well_persists_as_the_well(work, truth, hist):
    h = images(hist["nosat"])
    assert h["names"] == ["PRIMARY", "FLUENCE", "DRAWN", "STARFLU"]
    assert h["FLUENCE"].max() > 3 * WELL                             # no saturation in the earlier frame
    every = ("--persistence-source", "all")                         # the FLUENCE persists (not the default)
    capped = images(later(work, truth, "cap_well.fits", "--previous", hist["nosat"], *every,
                          "--set", "persistence.fluence_cap=well"))
    np.testing.assert_allclose(capped["PERSIST"], law(np.minimum(h["FLUENCE"], WELL)), rtol=1e-5, atol=1e-6)
    none = images(later(work, truth, "cap_none.fits", "--previous", hist["nosat"], *every,
                        "--set", "persistence.fluence_cap=none"))
    np.testing.assert_allclose(none["PERSIST"], law(h["FLUENCE"]), rtol=1e-5, atol=1e-6)
    assert none["PERSIST"].max() > 1.2 * capped["PERSIST"].max()     # the law grows beyond the well
    half = images(later(work, truth, "cap_half.fits", "--previous", hist["nosat"], *every,
                        "--set", "persistence.fluence_cap=5e4"))
    np.testing.assert_allclose(half["PERSIST"], law(np.minimum(h["FLUENCE"], 5e4)), rtol=1e-5, atol=1e-6)
    assert images(later(work, truth, "cap_none.fits", "--previous", hist["nosat"], *every,
                        "--set", "persistence.fluence_cap=none"))["headers"]["PERSIST"]["PS_CAP"] == "none"
    # a model without a well has nothing to clip at: 'well' then means no cap
    nosat = images(later(work, truth, "cap_nosat.fits", "--previous", hist["nosat"], *every,
                         "--set", "saturation=off", "--set", "persistence.fluence_cap=well"))
    np.testing.assert_allclose(nosat["PERSIST"], law(h["FLUENCE"]), rtol=1e-5, atol=1e-6)
    assert nosat["headers"]["PRIMARY"]["PS_CAP"] == "none"


def test_stars_beyond_the_well_persist_as_the_well_with_cap_well(work, truth, hist):
    h = images(hist["full"])
    well = images(later(work, truth, "stars_well.fits", "--previous", hist["full"], "--persistence-source", "stars",
                        "--set", "persistence.fluence_cap=well"))
    np.testing.assert_allclose(well["PERSIST"], law(np.minimum(h["STARFLU"], WELL)), rtol=1e-5, atol=1e-6)


def test_fluence_input_of_a_model():
    from perscli.detector.effects import Persistence
    from perscli.detector.model import load_detector_model

    # the default source is the light drawn (DRAWN), uncapped, render and study alike
    assert Persistence.fluence_input(load_detector_model("roman")) == ("drawn", None, None)
    assert Persistence.fluence_input(load_detector_model("roman", ["saturation.full_well=8e4",
                                                                   "persistence.source=all",
                                                                   "persistence.fluence_cap=well"])) == \
        ("all", None, 8e4)
    assert Persistence.fluence_input(load_detector_model("roman", ["saturation=off",
                                                                   "persistence.fluence_cap=well"])) == \
        ("drawn", None, None)
    assert Persistence.fluence_input(load_detector_model("roman", ["saturation=off", "persistence.source=all"])) == \
        ("all", None, None)
    assert Persistence.fluence_input(load_detector_model("roman", ["persistence.source=1000",
                                                                   "persistence.fluence_cap=none"])) == \
        ("threshold", 1000.0, None)


# -- which HDUs ------------------------------------------------------------------------------------

def test_hdus_are_written_in_order_and_checked(work, truth, hist):
    f = images(later(work, truth, "sel.fits", "--previous", hist["full"], "--hdus", "persist,sci"))
    assert f["names"] == ["PRIMARY", "SCI", "PERSIST"]
    prim = f["headers"]["PRIMARY"]
    assert prim["HDUS"] == "SCI,PERSIST" and prim["NOBJ"] == 4 and prim["SKYRATE"] > 0
    # PERSIST asked for without earlier exposures: there is none to write
    assert images(later(work, truth, "noprev.fits", "--hdus", "SCI,PERSIST"))["names"] == ["PRIMARY", "SCI"]
    for bad, needle in (("SCI,FOO", "FOO"), (",", "at least one")):
        result = later(work, truth, "badhdus.fits", "--hdus", bad, expect=1)
        assert needle in result.stderr and len(result.stderr.splitlines()) == 1
    assert not (work / "badhdus.fits").exists()


def test_a_frame_without_fluence_is_refused_as_previous(work, truth, hist):
    sci_only = render(work / "sci_only.fits", truth, "--hdus", "SCI,MODEL")
    before = listing(work)
    # the FLUENCE case: --persistence-source all
    result = later(work, truth, "refused.fits", "--previous", sci_only, "--persistence-source", "all", expect=1)
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "sci_only.fits: no FLUENCE extension" in lines[0] and "FLUENCE in --hdus" in lines[0]
    assert listing(work) == before
    # the DRAWN case: the default source (drawn), with its ways out
    result = later(work, truth, "refused.fits", "--previous", sci_only, expect=1)
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "sci_only.fits: no DRAWN extension" in lines[0]
    assert "DRAWN in --hdus" in lines[0] and "--persistence-source" in lines[0]
    assert listing(work) == before
    no_stars = render(work / "no_stars.fits", truth, "--hdus", "FLUENCE")
    before = listing(work)
    result = later(work, truth, "refused.fits", "--previous", no_stars, "--persistence-source", "stars", expect=1)
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "no_stars.fits: no STARFLU extension" in lines[0]
    assert "STARFLU in --hdus" in lines[0] and "or use --persistence-source drawn" in lines[0]
    # an explicit HDU must be the one that persists
    result = later(work, truth, "refused.fits", "--previous", hist["full"] + "[SCI]", "--persistence-source", "all",
                   expect=1)
    assert "FLUENCE" in result.stderr and len(result.stderr.splitlines()) == 1
    result = later(work, truth, "refused.fits", "--previous", hist["full"] + "[FLUENCE]", expect=1)
    assert "comes from its DRAWN" in result.stderr and len(result.stderr.splitlines()) == 1
    assert listing(work) == before
    # the way out works: a frame without DRAWN or STARFLU is a history under --persistence-source all
    later(work, truth, "way_out.fits", "--previous", no_stars, "--persistence-source", "all")


def test_history_without_sci_and_explicit_extension(work, truth, hist, persisted):
    # FLUENCE and STARFLU only (no SCI): still an earlier exposure, for either source
    light = render(work / "light.fits", truth, "--hdus", "FLUENCE,STARFLU,DRAWN")
    a = images(later(work, truth, "light_all.fits", "--previous", light, "--persistence-source", "all"))
    np.testing.assert_array_equal(a["PERSIST"], images(persisted["all"])["PERSIST"])
    s = images(later(work, truth, "light_stars.fits", "--previous", light, "--persistence-source", "stars"))
    np.testing.assert_array_equal(s["PERSIST"], images(persisted["stars"])["PERSIST"])
    e = images(later(work, truth, "explicit.fits", "--previous", hist["full"] + "[FLUENCE]",
                     "--persistence-source", "all"))
    np.testing.assert_array_equal(e["PERSIST"], images(persisted["all"])["PERSIST"])
    # under source stars, the explicit extension is STARFLU; under the default, DRAWN
    es = images(later(work, truth, "explicit_stars.fits", "--previous", hist["full"] + "[STARFLU]",
                      "--persistence-source", "stars"))
    np.testing.assert_array_equal(es["PERSIST"], images(persisted["stars"])["PERSIST"])
    ed = images(later(work, truth, "explicit_drawn.fits", "--previous", hist["full"] + "[DRAWN]"))
    np.testing.assert_array_equal(ed["PERSIST"], images(persisted["drawn"])["PERSIST"])
    prim = a["headers"]["PRIMARY"]
    assert prim["PRV01"] == "light.fits"
    with fits.open(light) as hdul:
        assert prim["PRV01DS"] == hdul["FLUENCE"].header["DATASUM"]
    with fits.open(light) as hdul:
        assert s["headers"]["PRIMARY"]["PRV01DS"] == hdul["STARFLU"].header["DATASUM"]


# -- compressed frames ----------------------------------------------------------------------------

def test_compressed_history_serves_every_source(work, truth, hist, persisted):
    with fits.open(hist["gz"]) as hdul:
        assert [h.name for h in hdul] == ["PRIMARY", "SCI", "IDEAL", "FLUENCE", "DRAWN", "STARFLU", "MODEL"]
        assert isinstance(hdul["STARFLU"], fits.CompImageHDU)
        with fits.open(hist["full"]) as plain:
            for name in ("SCI", "IDEAL", "FLUENCE", "DRAWN", "STARFLU"):
                np.testing.assert_array_equal(hdul[name].data, plain[name].data)
    assert os.path.getsize(hist["gz"]) < os.path.getsize(hist["full"])
    for source, name in (("all", "all"), ("drawn", "drawn"), ("stars", "stars"), ("5e4", "thr")):
        f = images(later(work, truth, f"gz_{name}.fits", "--previous", hist["gz"], "--persistence-source", source,
                         "--compress", "gzip"))
        np.testing.assert_array_equal(f["PERSIST"], images(persisted[name])["PERSIST"])
        np.testing.assert_array_equal(f["SCI"], images(persisted[name])["SCI"])


def test_compressed_frame_reads_as_the_plain_one(hist):
    """The read path of measure and apply-persistence (perscli.io.frames): same pixels, units and timing."""
    from perscli.io.frames import open_frame

    with open_frame(hist["gz"]) as gz, open_frame(hist["full"]) as plain:
        assert (gz.unit, gz.gain, gz.start, gz.end, gz.shape) == (plain.unit, plain.gain, plain.start, plain.end,
                                                                  plain.shape)
        np.testing.assert_array_equal(gz.planes()[0], plain.planes()[0])
        np.testing.assert_array_equal(gz.fluence()[0], plain.fluence()[0])


def test_compressed_frame_is_measured_as_the_plain_one(work, truth, hist):
    out_plain, out_gz = work / "shapes_plain.fits", work / "shapes_gz.fits"
    for frame, out in ((hist["full"], out_plain), (hist["gz"], out_gz)):
        result = invoke("measure", frame, "--catalog", truth, "-o", out, "--overwrite")
        assert result.exit_code == 0, result.stderr
    with fits.open(out_plain) as a, fits.open(out_gz) as b:
        sa, sb = a["SHAPES"].data, b["SHAPES"].data
        for col in ("g1", "g2", "flux", "flags"):
            np.testing.assert_array_equal(sa[col], sb[col])
        assert np.any(sa["flags"] == 0)


# -- frames without objects ------------------------------------------------------------------------

@pytest.mark.parametrize("where", ["elsewhere", "empty"])
def test_a_frame_without_objects(work, optics, where):
    objects = [("star", 3000.0, 3000.0, 15.0, 0.0)] if where == "elsewhere" else []
    if objects:
        cat = write_catalog(work / f"none_{where}.fits", optics, objects)
    else:
        t = Table({"id": np.zeros(0, dtype=np.int64), "ra": np.zeros(0), "dec": np.zeros(0),
                   "kind": np.zeros(0, dtype="U6"), "mag_J129": np.zeros(0), "mag_H158": np.zeros(0),
                   "hlr": np.zeros(0), "e1": np.zeros(0), "e2": np.zeros(0)})
        cat = str(work / "none_empty.fits")
        t.write(cat, format="fits", overwrite=True)
    first = render(work / f"nobj1_{where}.fits", cat, "--hdus", "SCI,FLUENCE,STARFLU")
    f = images(first)
    assert f["headers"]["PRIMARY"]["NOBJ"] == 0 and np.all(f["STARFLU"] == 0)
    assert abs(np.median(f["FLUENCE"]) - f["headers"]["PRIMARY"]["SKYRATE"] * T) < 10
    second = images(later(work, cat, f"nobj2_{where}.fits", "--previous", first, "--persistence-source", "stars"))
    assert np.all(second["PERSIST"] == 0)


# -- exposures of schedule rows ----------------------------------------------------------------------

def test_exposure_from_a_schedule_row(shared_data, tmp_path):
    from perscli.render.exposure import Exposure
    from perscli.scene.schedule import read_schedule, schedule_pointing

    schedule = read_schedule(str(shared_data / "roman" / "Roman_WAS_obseq_11_1_23.fits"))
    e = Exposure.from_pointing(schedule_pointing(schedule, 4183), sca=3, bounds=(1, 64, 1, 64))
    assert (e.expid, e.sca, e.filter, e.bounds) == (4183, 3, "J129", (1, 64, 1, 64))
    assert (e.mjd, e.exptime, e.ra, e.dec, e.pa) == (schedule.mjd[4183], schedule.exptime[4183],
                                                     schedule.ra[4183], schedule.dec[4183], schedule.pa[4183])
    from perscli import PerscliError

    with pytest.raises(PerscliError, match="SCA"):
        Exposure.from_pointing(schedule_pointing(schedule, 4183))


def test_a_date_roman_cannot_observe_is_one_line(work, truth):
    # RA 10, Dec -44 is too close to the Sun on MJD 60000 (2023-02-25)
    result = render(work / "never.fits", truth, mjd=60000.0, expect=1)
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "Roman cannot point at" in lines[0] and "Sun" in lines[0]
