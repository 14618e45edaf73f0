"""The differential study: noise keyed on detector blocks, frames simulated only where persistence reaches,
and the result galaxy by galaxy identical to the full computation."""

import json

import numpy as np
import pytest

from fits_factory import run
from perscli.detector.blocks import NOISE_BLOCK, block_grid
from perscli.detector.chain import run_chain, run_chains
from perscli.detector.model import default_model


def _sources(shape, seed=3):
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 50, shape)
    img[40:44, 70:74] += 2e5          # a saturated star
    return img


# -- the noise -----------------------------------------------------------------------------------

def test_a_pixel_gets_the_same_noise_whatever_else_is_simulated():
    model = default_model()
    big = _sources((160, 192))
    whole = run_chain(big, model, exptime=139.8, seed=7, sky_rate=0.5, origin=(33, 65))
    # a part of it that starts and ends on block edges (detector x 65..160, y 97..160), simulated alone
    y0, x0 = 97 - 65, 65 - 33
    part = run_chain(big[y0:y0 + 64, x0:x0 + 96], model, exptime=139.8, seed=7, sky_rate=0.5, origin=(65, 97))
    inner = (slice(1, -1), slice(1, -1))     # interpixel capacitance reaches one pixel beyond
    np.testing.assert_array_equal(part.sci[inner], whole.sci[y0:y0 + 64, x0:x0 + 96][inner])
    np.testing.assert_array_equal(part.fluence, whole.fluence[y0:y0 + 64, x0:x0 + 96])
    # another seed is other noise
    other = run_chain(big, model, exptime=139.8, seed=8, sky_rate=0.5, origin=(33, 65))
    assert not np.array_equal(other.sci, whole.sci)


def test_only_the_active_blocks_are_simulated_and_they_are_the_whole_frames_pixels():
    model = default_model()
    img = _sources((128, 128))
    whole = run_chain(img, model, exptime=139.8, seed=5, sky_rate=0.5)
    _, _, nby, nbx = block_grid((1, 1), img.shape)
    active = np.zeros((nby, nbx), dtype=bool)
    active[1, 2] = active[2, 1] = active[2, 2] = True
    part = run_chain(img, model, exptime=139.8, seed=5, sky_rate=0.5, active=active)
    b = NOISE_BLOCK
    # block (row 2, column 2) but its edge pixels: interpixel capacitance brings in neighbours of inactive blocks
    core = (slice(2 * b + 1, 3 * b - 1), slice(2 * b + 1, 3 * b - 1))
    np.testing.assert_array_equal(part.sci[core], whole.sci[core])
    assert np.isnan(part.sci[:b, :b]).all() and np.isnan(part.fluence[:b, :b]).all()
    assert np.isfinite(part.sci[core]).all()


@pytest.mark.parametrize("extra", [(), ("brighter_fatter.coefficient=3e-8", "correlated_read_noise.row=2",
                                    "correlated_read_noise.column=1.5")], ids=["roman", "bf_and_correlated"])
def test_a_stack_of_blocks_gives_the_pixels_of_the_whole_area(extra):
    """The chain on a stack of scattered noise blocks, interpixel capacitance and brighter-fatter through their
    neighbours, row and column noise by their place on the detector."""
    from perscli.detector.blocks import BlockStack
    from perscli.detector.model import load_detector_model

    model = load_detector_model("roman", list(extra))
    # the detector's far corner: its last row and column of blocks are partial (4088 = 127 x 32 + 24)
    origin = (32 * 122 + 1, 32 * 124 + 1)
    img = _sources((4088 - origin[1] + 1, 4088 - origin[0] + 1))
    pers = np.linspace(0, 40, img.size).reshape(img.shape)
    _, _, nby, nbx = block_grid(origin, img.shape)
    rng = np.random.default_rng(4)
    active = rng.random((nby, nbx)) < 0.5
    active[-1, -1] = active[0, 0] = True
    whole = run_chain(img, model, exptime=139.8, seed=9, sky_rate=0.5, persistence=pers, origin=origin,
                      active=active)
    blocks = BlockStack.of(active, origin, img.shape)
    stack = run_chains(blocks.gather(img), {"": model}, exptime=139.8, seed=9, sky_rate=0.5,
                       persistence={"": blocks.gather(pers, fill=0.0)}, origin=origin, blocks=blocks)[""]
    np.testing.assert_array_equal(blocks.scatter(stack.sci), whole.sci)
    np.testing.assert_array_equal(blocks.scatter(stack.fluence), whole.fluence)


def test_chains_sharing_their_first_steps_give_each_models_own_frame():
    from perscli.detector.model import load_detector_model

    img = _sources((96, 96))
    pers = np.linspace(0, 40, img.size).reshape(img.shape)
    a = load_detector_model("roman", ["persistence.base=typical"])
    b = load_detector_model("roman", ["persistence.base=pessimistic", "read_noise.sigma=5"])
    both = run_chains(img, {"ref": a, "p": b}, exptime=139.8, seed=2, sky_rate=0.5,
                      persistence={"ref": None, "p": pers})
    np.testing.assert_array_equal(both["ref"].sci, run_chain(img, a, exptime=139.8, seed=2, sky_rate=0.5).sci)
    np.testing.assert_array_equal(both["p"].sci, run_chain(img, b, exptime=139.8, seed=2, sky_rate=0.5,
                                                            persistence=pers).sci)
    np.testing.assert_array_equal(both["p"].persistence, pers)


def test_a_cutout_is_that_part_of_a_larger_frame(tmp_path):
    run("catalog", "--ra", 9.5386, "--dec", -44.0435, "--size", 2, "--star-density", 10, "--seed", 1,
        "-o", tmp_path / "t.fits")
    common = ["--ra", 10, "--dec", -44, "--pa", 30, "--filter", "J129", "--sca", 7, "--mjd", 61541.97,
              "--seed", 11, "--hdus", "SCI,FLUENCE,DRAWN,STARFLU"]
    run("render", tmp_path / "t.fits", *common, "--bounds", 1001, 1100, 2001, 2090, "-o", tmp_path / "a.fits")
    run("render", tmp_path / "t.fits", *common, "--bounds", 950, 1130, 1990, 2120, "-o", tmp_path / "b.fits")
    import fitsio

    for ext in ("SCI", "FLUENCE", "DRAWN", "STARFLU"):
        a = fitsio.read(str(tmp_path / "a.fits"), ext)
        b = fitsio.read(str(tmp_path / "b.fits"), ext)
        np.testing.assert_array_equal(a, b[2001 - 1990:2091 - 1990, 1001 - 950:1101 - 950])
    stars = tmp_path / "s.fits"
    run("render", tmp_path / "t.fits", *common[:-2], "--bounds", 950, 1130, 1990, 2120, "--hdus", "STARFLU",
        "-o", stars)
    np.testing.assert_array_equal(fitsio.read(str(stars), "STARFLU"), fitsio.read(str(tmp_path / "b.fits"), "STARFLU"))


# -- where persistence reaches ----------------------------------------------------------------------------

def test_reach_mask_windows_and_touches():
    from perscli.study.reach import reach_mask, touches, window_boxes

    bounds = (101, 200, 301, 380)
    mask = reach_mask([[90, 110, 290, 305], [150, 151, 350, 350]], bounds)
    assert mask.shape == (80, 100) and mask.sum() == 10 * 5 + 2
    boxes = window_boxes([120.4, 160.6], [320.2, 340.0], 16, margin=0)
    assert boxes.tolist() == [[112, 127, 312, 327], [153, 168, 332, 347]]
    assert touches(mask, boxes, bounds).tolist() == [False, False]
    assert touches(mask, window_boxes([120.4, 160.6], [320.2, 340.0], 16, margin=3), bounds).tolist() == [False, True]
    assert touches(mask, [[60, 90, 300, 400]], bounds).tolist() == [False]      # off the frame


# -- the whole study, both ways ----------------------------------------------------------------------------

#: a 1024-pixel corner with the paper's star density: persistence reaches part of it, not all
FIELD = ["exposures.source=plan", "catalog.star_density=2.5", "bounds=[1,1024,1,1024]"]


def _study(tmp, differential, *extra):
    out = tmp / f"{'diff' if differential else 'full'}"
    run("study", "--preset", "ci", "-o", out, "--scheduler", "serial", "-q",
        *sum([["--set", c] for c in [*FIELD, f"differential={str(differential).lower()}", *extra]], []))
    return out


def _table(path, ext):
    import fitsio

    return fitsio.read(str(path), ext)


def _changes(diff, variant, joint):
    if joint:
        return np.concatenate([_table(f, variant.upper()) for f in sorted((diff / "shapes").glob("part*.fits"))])
    return np.concatenate([_table(f, variant.upper()) for f in sorted((diff / "shapes").glob("sca*/e*.fits"))])


def _assert_same_de(full, diff, variant, joint):
    """The differential De of every galaxy of the sample is the full computation's, to the linear response's
    tolerance (max(1e-3 |De|, 1e-10)): the same sample, the same decisions at 1e-8 and 1e-4."""
    ch = _changes(diff, variant, joint)
    assert len(np.unique(ch["id"] if joint else ch["id"] * 100000 + ch["expid"])) == len(ch)
    if joint:
        sides = [(_table(full / "shapes" / "ref.fits", "JOINT"), _table(full / "shapes" / f"{variant}.fits", "JOINT"),
                  ch)]
    else:
        sides = []
        for f in sorted((full / "shapes" / "ref").glob("*.fits")):
            expid = int(f.stem.split("_e")[1])
            sides.append((_table(f, "SHAPES"), _table(full / "shapes" / variant / f.name, "SHAPES"),
                          ch[ch["expid"] == expid]))
    nonzero = 0
    for ref, var, rows in sides:
        where = {int(i): k for k, i in enumerate(ref["id"])}
        for r in rows:
            k = where[int(r["id"])]
            de = np.array([var["g1"][k] - ref["g1"][k], var["g2"][k] - ref["g2"][k]])
            if r["fitted"]:
                # the fit of the change from the reference's minimum: the change of the minimum, where the full
                # computation gives it as the difference of two fits from the start, each to its own tolerance
                got = np.array([r["de1"], r["de2"]])
                assert np.max(np.abs(got - de)) <= max(1e-3 * np.max(np.abs(de)), 1e-10), (r["id"], got, de)
                for threshold in (1e-8, 1e-4):
                    assert (np.hypot(*got) >= threshold) == (np.hypot(*de) >= threshold)
                assert r["flags"] == ref["flags"][k] | var["flags"][k]
            else:
                # not fitted: the full computation's two fits are the same numbers
                assert r["de1"] == 0 and r["de2"] == 0
                assert var["g1"][k] == ref["g1"][k] and var["g2"][k] == ref["g2"][k]
                assert var["flags"][k] == ref["flags"][k]
            nonzero += bool(de[0] or de[1])
    return ch, nonzero


def _same_statistics(full, diff, variant):
    """The same sample and the same fractions in both studies' xi tables (STATS)."""
    a, b = _table(full / "xi" / f"{variant}.fits", "STATS"), _table(diff / "xi" / f"{variant}.fits", "STATS")
    assert a["n"][0] == b["n"][0] > 0
    np.testing.assert_array_equal(a["n_ge"], b["n_ge"])
    np.testing.assert_array_equal(a["n_dabs_ge"], b["n_dabs_ge"])


def test_persisting_stars_are_whole_groups_of_overlapping_stamps():
    from perscli.study.reach import persisting_stars

    boxes = np.array([[0, 10, 0, 10], [5, 15, 5, 15], [14, 20, 14, 20], [100, 110, 100, 110], [200, 210, 0, 5]])
    flux = [10, 10, 10, 50, 200]
    assert persisting_stars(flux, boxes, 0).all()
    # the chain of three sums to 30: it lights no pixel above 40, the others can
    assert persisting_stars(flux, boxes, 40).tolist() == [False, False, False, True, True]
    assert persisting_stars(flux, boxes, 25).all()
    assert persisting_stars(flux, boxes, 1000).tolist() == [False] * 5


@pytest.mark.parametrize("n", [16, 64, 256])
def test_the_psf_envelope_bounds_a_star_wherever_it_falls_on_its_pixel(n):
    from perscli.study.reach import psf_envelope
    from perscli.optics import stamp_drawer

    env = psf_envelope(7, "J129", n)
    drawer = stamp_drawer(7, "J129")
    c = n // 2
    j, i = np.indices((n, n))
    dist = np.maximum(abs(i - c), abs(j - c))
    assert np.all(np.diff(env) <= 0)                       # the most at distance d or more
    for dx, dy in [(0.2, -0.3), (-0.45, 0.1), (0.33, 0.33), (-0.1, -0.49), (0.0, 0.25)]:
        assert np.all(np.abs(drawer.stamp(n, dx, dy, 1.0)) <= env[dist])


#: the headline (every object's drawn light persisting, one joint shape per galaxy) and two brackets: star light
#: only, and only light above 300 e- per pixel persisting; and the headline's laws with one shape per exposure
SETTINGS = {
    "headline": ([], ("drawn-typical", "drawn-pessimistic")),
    "stars": (["persistence.sources=[stars]"], ("stars-typical", "stars-pessimistic")),
    "floor": (["persistence.bracket={floor300: [persistence.floor=300]}"], ("floor300-typical",)),
    "per-exposure": (["measure.joint=false", "persistence.models=[typical]"], ("drawn-typical",)),
}


@pytest.mark.slow
@pytest.mark.parametrize("setting", list(SETTINGS))
def test_the_differential_study_gives_the_full_computations_sample_fractions_and_de(tmp_path, setting):
    extra, variants = SETTINGS[setting]
    joint = "measure.joint=false" not in extra
    full = _study(tmp_path, False, *extra)
    diff = _study(tmp_path, True, *extra)
    summary = json.loads((diff / "summary.json").read_text())
    res = {r["variant"]: r for r in summary["results"]}
    for variant in variants:
        _same_statistics(full, diff, variant)
        ch, nonzero = _assert_same_de(full, diff, variant, joint)
        assert nonzero > 0 and ch["fitted"].sum() > 0
        if setting != "headline" and setting != "per-exposure":
            # light of stars (or bright light) only: most galaxies untouched, exactly
            assert ch["fitted"].sum() < len(ch)
        assert res[variant]["sample"] == len(ch)


def test_brighter_fatter_conserves_charge_and_widens_bright_sources_only():
    from perscli.detector.blocks import ChainContext
    from perscli.detector.effects import REGISTRY

    img = np.zeros((21, 21))
    img[10, 10], img[10, 9], img[10, 11], img[9, 10], img[11, 10] = 9e4, 3e4, 3e4, 3e4, 3e4
    bf = REGISTRY["brighter_fatter"]({"coefficient": 4e-8})
    bright = bf.expectation(img, ChainContext(exptime=1.0))
    faint = bf.expectation(img * 1e-2, ChainContext(exptime=1.0))
    assert bright.sum() == pytest.approx(img.sum(), rel=1e-12)
    assert bright[10, 10] < img[10, 10] and bright[9, 9] > 0           # charge pushed outwards
    # the flow goes as the charge squared: a source 100 times fainter moves 1e4 times less charge
    assert abs(faint[10, 10] - img[10, 10] * 1e-2) == pytest.approx(abs(bright[10, 10] - img[10, 10]) * 1e-4,
                                                                   rel=1e-9)


def test_correlated_read_noise_is_shared_by_rows_and_columns():
    from perscli.detector.blocks import ChainContext
    from perscli.detector.effects import REGISTRY

    eff = REGISTRY["correlated_read_noise"]({"row": 3.0, "column": 0.0})
    img = eff.sample(np.zeros((400, 300)), ChainContext(exptime=1.0, seed=4))
    assert np.all(img == img[:, :1])                       # one offset per row
    assert img[:, 0].std() == pytest.approx(3.0, rel=0.15)
    # a cutout gets its rows' offsets whatever the area simulated
    part = eff.sample(np.zeros((50, 20)), ChainContext(exptime=1.0, seed=4, origin=(11, 101)))
    np.testing.assert_array_equal(part, img[100:150, 10:30])
