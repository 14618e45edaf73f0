"""The registry of detector effects (perscli.detector.effects): renders byte-identical to the chain
before the registry, schemas that validate, expectation and variance that match sampled frames,
saturation, --list-effects, and the detector model that a rendered frame carries and reloads."""

import hashlib

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table

from fits_factory import invoke

RA, DEC, PA, SCA, FILTER = 10.0, -44.0, 30.0, 7, "J129"
MJD1 = 61541.97
T = 139.8
MJD2 = MJD1 + (T + 30.0) / 86400.0
MJD3 = MJD2 + (T + 30.0) / 86400.0
BOUNDS = (1001, 1064, 2001, 2064)            # 64 x 64

#: (kind, SCA x, SCA y, J129, hlr, e1, e2): a bright star (peak ~1.3e6 e-), a faint one, two galaxies
OBJECTS = [("star", 1020.3, 2030.6, 15.0, 0.3, 0, 0), ("star", 1050.7, 2012.2, 20.0, 0.3, 0, 0),
           ("galaxy", 1040.4, 2050.1, 17.5, 0.3, 0.2, -0.1), ("galaxy", 1012.6, 2055.8, 21.0, 0.5, 0, 0.1)]

#: sha256 of each image HDU's data as big-endian float32, rendered by the chain before the registry
#: (commit f61446f, and again at 5627a19/d07a744: identical, with --workers 1 and 2), then re-pinned
#: when render began passing the exposure's date to GalSim's sky (commit 9766425): IDEAL then moved by
#: exactly (1.2866 - 0.5665) e-/s x 139.8 s = 100.67 e- in every pixel of e1, and nothing else changed
#: in the chain; re-pinned again when the noise became keyed on detector blocks of 32 pixels (issue 16:
#: a pixel's noise the same whatever part of the detector is simulated): IDEAL unchanged in all three
#: frames, SCI, FLUENCE and PERSIST (which follows e1's and e2's FLUENCE) drawn from the new streams.
#: Re-pinned once more when objects came to be drawn in batches by one compiled pass (the exponential's own
#: transform instead of GalSim's kImage, the same pixel values to ~1e-12 of the peak) and galaxy stamps to 8
#: half-light radii (issue 24): every image moved in its last bits.
#: e1: the Roman chain; e2: 30 s later, dithered by 1.44", with e1 as --previous; e3:
#: 30 s after e2, with e1 and e2 as --previous, pessimistic persistence, gain 2, read noise 5.
REFERENCE = {
    "e1": {"SCI": "611f61f0f589a0eb004aa4a03a25fd865e17c8ee7b11bf148ad9537510cea382",
           "IDEAL": "394fafa9e9149b26d55fd578f37402d2763c6dc562bce12a19af2da0632aee7c",
           "FLUENCE": "072c941786a99eebb652ac358a170389fd79931b2834fbcaf0e3208c2dd71342"},
    "e2": {"SCI": "fad08d84fc972b623abb38f93150b40e81e3277beca11c122925ed43b582d08d",
           "IDEAL": "c7068ab326419c624e390ba42dd0519fa4f2074beac22cedeebc615097138802",
           "FLUENCE": "14c8c2e742be6d5feef31f3421dd6d5f0b61cc1f574828c0387b37cf96bedf9f",
           "PERSIST": "877c997a8551c6b530bef9c6b466e011479de9b453194a7ec4a0d0b1bb2270e5"},
    "e3": {"SCI": "21832fb497db1c9f657b0af91c64b2be9a0a39c7ffed7d5d756ec5c3182cd626",
           "IDEAL": "b68f5fc0b1be66224a63ee5ce19d985792958aa4b8537e75b4c7f5ec5e736dc2",
           "FLUENCE": "0fc571a74671956027dff9282a7ddcc35bb5e0b9a2141c95e076fe2d6a07f0b3",
           "PERSIST": "3e042c0cf63f7e919c27c19f9de8a5264b043b13f68f4362bb6d501c06b2296c"},
}


def write_truth(path):
    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    optics = Optics(Exposure(ra=RA, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD1))
    rows = []
    for i, (kind, x, y, mag, hlr, e1, e2) in enumerate(OBJECTS, 1):
        ra, dec = optics.wcs.xyToradec(x, y, units="deg")
        rows.append((i, float(ra), float(dec), kind, mag, mag + 0.3, hlr, e1, e2))
    t = Table(rows=rows, names=["id", "ra", "dec", "kind", "mag_J129", "mag_H158", "hlr", "e1", "e2"])
    t["id"] = t["id"].astype(np.int64)
    t.write(str(path), format="fits", overwrite=True)
    return str(path)


def render(out, truth, *extra, mjd=MJD1, ra=RA, seed=11, expect=0):
    args = ["render", truth, "--bounds", *BOUNDS, "--ra", ra, "--dec", DEC, "--pa", PA, "--mjd", repr(mjd),
            "--filter", FILTER, "--sca", SCA, "--seed", seed, "-o", out, "--overwrite", *extra]
    result = invoke(*args)
    assert result.exit_code == expect, (result.exit_code, result.stderr, result.exception)
    return str(out)


def digests(path):
    with fits.open(path) as hdul:
        return {h.name: hashlib.sha256(np.asarray(h.data, dtype=">f4").tobytes()).hexdigest()
                for h in hdul[1:] if h.is_image}


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("registry")


@pytest.fixture(scope="module")
def truth(work):
    return write_truth(work / "truth.fits")


def reference_sequence(work, truth, workers, *extra):
    # the HDUs and the persistence source (FLUENCE) of the chain before the registry, not today's defaults
    off = ["--set", "saturation=off", "--workers", workers, "--hdus", "SCI,IDEAL,FLUENCE,PERSIST,MODEL",
           "--persistence-source", "all", *extra]
    e1 = render(work / f"e1_w{workers}.fits", truth, *off, seed=11)
    e2 = render(work / f"e2_w{workers}.fits", truth, *off, "--previous", e1, mjd=MJD2, ra=RA + 0.0004, seed=12)
    e3 = render(work / f"e3_w{workers}.fits", truth, *off, "--previous", e1, "--previous", e2,
                "--set", "persistence.base=pessimistic", "--set", "gain.gain=2", "--set", "read_noise.sigma=5",
                mjd=MJD3, seed=13)
    return {"e1": e1, "e2": e2, "e3": e3}


@pytest.mark.parametrize("workers", ["1", "2"])
def test_renders_are_byte_identical_to_the_chain_before_the_registry(work, truth, workers):
    """Same seed, today's model with saturation off: SCI, IDEAL, FLUENCE and PERSIST unchanged."""
    frames = reference_sequence(work, truth, workers)
    for name, path in frames.items():
        got = digests(path)
        assert set(got) >= set(REFERENCE[name]), (name, sorted(got))
        for ext, digest in REFERENCE[name].items():
            assert got[ext] == digest, (name, ext)


# -- the registry and its schemas -----------------------------------------------------------------

def test_registry_order_and_schemas():
    from perscli.detector import effects
    from perscli.detector.model import default_model

    assert effects.ORDER == ("sky", "poisson", "reciprocity", "dark", "persistence", "brighter_fatter", "saturation",
                             "nonlinearity", "ipc", "read_noise", "correlated_read_noise", "offset", "gain",
                             "quantize")
    # the Roman model has every effect but the offset (a bias level), brighter-fatter and correlated read
    # noise (GalSim's Roman chain has neither): candidates for diagnose, switched on with --set
    off = ("offset", "brighter_fatter", "correlated_read_noise")
    assert effects.ROMAN_ORDER == tuple(n for n in effects.ORDER if n not in off)
    assert [e.name for e in default_model().effects] == list(effects.ROMAN_ORDER)
    for name, cls in effects.REGISTRY.items():
        assert cls.name == name and cls.description and cls.stage in ("scene", "charge", "readout")
        for p in cls.schema:
            assert p.kind in ("float", "int", "choice", "kernel", "floats") and p.description
            # every default passes its own schema
            assert p.check(name, p.default, "test") == p.default or p.default is None
    stages = [effects.REGISTRY[n].stage for n in effects.ORDER]
    assert stages == sorted(stages, key=["scene", "charge", "readout"].index)     # scene, then charge, then readout
    units = {(n, p.name): p.unit for n, c in effects.REGISTRY.items() for p in c.schema}
    assert units[("gain", "gain")] == "e-/DN" and units[("saturation", "full_well")] == "e-"
    assert units[("dark", "current")] == "e-/pixel/s" and units[("read_noise", "sigma")] == "e-"


@pytest.mark.parametrize("setting, needles", [
    ("gain.gain=0", ["gain.gain", "must be positive", "(0, inf) e-/DN", "not 0"]),
    ("read_noise.sigma=-1", ["read_noise.sigma", "must not be negative", "[0, inf) e-", "not -1"]),
    ("read_noise.sigma=lots", ["read_noise.sigma", "finite number", "not 'lots'"]),
    ("saturation.full_well=0", ["saturation.full_well", "must be positive", "(0, inf) e-"]),
    ("persistence.max_previous=-1", ["persistence.max_previous", "integer [0, inf)", "not -1"]),
    ("persistence.max_previous=2.5", ["persistence.max_previous", "whole number", "not 2.5"]),
    ("persistence.combine=mean", ["persistence.combine must be one of sum, max", "not 'mean'"]),
    ("persistence.time_model=fast", ["persistence.time_model must be one of exact, middle, galsim", "not 'fast'"]),
    ("persistence.x0=0", ["persistence.x0", "must be positive"]),
    ("sky.level=-3", ["sky.level", "[0, inf) e-/pixel/s | auto", "not -3"]),
    ("ipc.kernel=[[1,0],[0,1]]", ["ipc.kernel must be 'roman' or a 3x3 list"]),
    ("saturation.well=3", ["unknown parameter(s) well for effect 'saturation'", "valid: full_well"]),
    ("persistence.coefficients=[]", ["persistence.coefficients", "non-empty list"]),
    ("persistence.source=-1", ["persistence.source", "[0, inf) e- | drawn | stars | all", "not -1"]),
    ("persistence.source=planets", ["persistence.source", "finite number", "not 'planets'"]),
    ("persistence.fluence_cap=0", ["persistence.fluence_cap", "(0, inf) e- | well | none", "not 0"]),
])
def test_schema_errors_name_effect_parameter_value_and_range(setting, needles):
    from perscli import PerscliError
    from perscli.detector.model import load_detector_model

    with pytest.raises(PerscliError) as err:
        load_detector_model("roman", [setting])
    text = str(err.value)
    assert "\n" not in text and text.startswith("--set: ")
    for needle in needles:
        assert needle in text, (needle, text)


def test_schema_errors_from_a_yaml_file_name_the_file(tmp_path):
    from perscli import PerscliError
    from perscli.detector.model import load_detector_model

    path = tmp_path / "m.yaml"
    path.write_text("effects:\n  - saturation: {full_well: -5}\n")
    with pytest.raises(PerscliError, match=r"m.yaml: saturation.full_well must be positive .*not -5"):
        load_detector_model(str(path))


def test_persistence_settings_are_model_parameters():
    from perscli.detector.model import load_detector_model

    m = load_detector_model("roman", ["persistence.max_previous=0", "persistence.time_model=galsim",
                                      "persistence.combine=max", "persistence.gamma=1.2"])
    pm = m.persistence_model()
    assert (pm.max_previous, pm.time_model, pm.combine, pm.gamma, pm.A) == (0, "galsim", "max", 1.2, 0.017)
    assert m.get("persistence").params["max_previous"] == 0
    # a later base changes the parameters taken from it, not those set explicitly
    m = load_detector_model("roman", ["persistence.gamma=1.2", "persistence.base=pessimistic"])
    pm = m.persistence_model()
    assert (pm.A, pm.x0, pm.gamma) == (0.086, 1.37e5, 1.2)
    linear = load_detector_model("roman", ["persistence.kind=linear", "persistence.coefficients=[1e-4, 5e-5]"])
    assert linear.persistence_model().coefficients == (1e-4, 5e-5)


def test_persistence_source_and_fluence_cap_are_model_parameters(tmp_path):
    from perscli.detector.effects import Persistence
    from perscli.detector.model import load_detector_model, model_from_table, model_table, model_to_yaml

    m = load_detector_model("roman")
    assert m.get("persistence").resolved()["source"] == "drawn"          # the default: the light drawn
    assert m.get("persistence").resolved()["fluence_cap"] == "none"      # uncapped, as GalSim
    for settings, expect in (([], ("drawn", None, None)),
                             (["persistence.source=all"], ("all", None, None)),
                             (["persistence.source=all", "persistence.fluence_cap=well"], ("all", None, 1e5)),
                             (["persistence.source=5e4", "persistence.fluence_cap=2e5"], ("threshold", 5e4, 2e5)),
                             (["persistence.source=stars"], ("stars", None, None)),
                             (["persistence.fluence_cap=well", "saturation=off"], ("drawn", None, None)),
                             (["persistence.fluence_cap=well", "saturation.full_well=8e4"], ("drawn", None, 8e4))):
        model = load_detector_model("roman", settings)
        assert Persistence.fluence_input(model) == expect, settings
        # the MODEL table and the YAML keep them
        data, _ = model_table(model)
        again = model_from_table({n: data[n] for n in data.dtype.names}, "test")
        assert again.describe() == model.describe()
        path = tmp_path / "m.yaml"
        path.write_text(model_to_yaml(model))
        assert load_detector_model(str(path)).describe() == model.describe()
        # the law itself does not depend on them
        assert model.persistence_model() == load_detector_model("roman").persistence_model()
    path = tmp_path / "stars.yaml"
    path.write_text("effects:\n  - persistence: {source: stars, fluence_cap: none}\n")
    assert Persistence.fluence_input(load_detector_model(str(path))) == ("stars", None, None)


def test_default_model_saturates_and_the_switch_restores_the_old_chain():
    from perscli.detector.chain import run_chain
    from perscli.detector.effects import FULL_WELL
    from perscli.detector.model import load_detector_model

    assert FULL_WELL == 1.0e5
    src = np.array([[5.0e4, 2.0e5, 3.0e6]])
    quiet = ["poisson=off", "dark=off", "read_noise=off", "sky=off", "ipc=off"]
    on = run_chain(src, load_detector_model("roman", quiet), exptime=T, seed=1)
    off = run_chain(src, load_detector_model("roman", quiet + ["saturation=off"]), exptime=T, seed=1)
    x = src * (1 + 0.0065 * np.log10(src / T))
    np.testing.assert_allclose(on.fluence, np.minimum(x, FULL_WELL), rtol=1e-14)
    np.testing.assert_allclose(off.fluence, x, rtol=1e-14)
    np.testing.assert_array_equal(on.ideal, src)                    # IDEAL is the scene: never clipped
    assert on.sci[0, 1] == on.sci[0, 2]                              # both saturated pixels read the same


# -- expectation and variance against sampled frames ------------------------------------------------

#: flat levels (electrons of sources), one per block of rows
LEVELS = (30.0, 400.0, 3.0e3, 2.0e4, 6.0e4, 9.0e4)
BLOCK = 48


def flat_blocks(levels=LEVELS, nx=1500):
    return np.repeat(np.asarray(levels, dtype=np.float64), BLOCK)[:, None] * np.ones((1, nx))


def block_stats(img, nblocks):
    """Per block: the interior pixels on a 3-pixel grid (independent after a 3x3 IPC kernel)."""
    out = []
    for b in range(nblocks):
        out.append(img[b * BLOCK + 2:(b + 1) * BLOCK - 2:3, 2:-2:3].reshape(-1))
    return out


def chi2_of(sample, mean, var, nblocks):
    """chi^2 of the block means and variances of ``sample`` against the predicted ``mean`` and ``var``
    (uniform over each block's interior), and its degrees of freedom."""
    chi2, dof = 0.0, 0
    for s, m, v in zip(block_stats(sample, nblocks), block_stats(mean, nblocks), block_stats(var, nblocks)):
        mu, sig2 = float(np.mean(m)), float(np.mean(v))
        assert np.ptp(m) <= 1e-9 * max(1.0, abs(mu)) and np.ptp(v) <= 1e-9 * max(1.0, sig2)
        n = s.size
        if sig2 == 0:
            assert np.all(s == mu)                                  # no noise predicted: none there
            continue
        chi2 += (s.mean() - mu) ** 2 / (sig2 / n) + (s.var(ddof=1) - sig2) ** 2 / (2 * sig2 ** 2 / (n - 1))
        dof += 2
    return chi2, dof


def p_value(chi2, dof):
    from scipy import stats

    return stats.chi2.sf(chi2, dof)


def chain_model(names, **params):
    from perscli.detector.effects import DEFAULTS
    from perscli.detector.model import DetectorModel, Effect

    effs = []
    for name in names:
        p = dict(DEFAULTS[name])
        p.update(params.get(name, {}))
        effs.append(Effect(name, p))
    return DetectorModel(effs, source="test")


#: name -> (effects, parameters, source levels): each effect alone, after Poisson where it acts on noise
CASES = {
    "poisson": (["poisson"], {}, LEVELS),
    "sky": (["sky", "poisson"], {"sky": {"level": 1.7}}, LEVELS),
    "reciprocity": (["poisson", "reciprocity"], {"reciprocity": {"alpha": 0.05}}, LEVELS),
    "dark": (["dark"], {"dark": {"current": 0.4}}, LEVELS),
    "persistence": (["poisson", "persistence"], {}, LEVELS),
    "saturation": (["poisson", "saturation"], {"saturation": {"full_well": 5.0e4}}, (4.0e3, 4.5e4, 7.0e4, 3.0e5)),
    "nonlinearity": (["poisson", "nonlinearity"], {"nonlinearity": {"beta": -2.0e-6}}, LEVELS),
    "ipc": (["poisson", "ipc"], {}, LEVELS),
    "read_noise": (["read_noise"], {"read_noise": {"sigma": 6.0}}, LEVELS),
    "gain": (["poisson", "gain"], {"gain": {"gain": 2.5}}, LEVELS),
    "quantize": (["read_noise", "quantize"], {"read_noise": {"sigma": 1.0}}, (10.3, 20.6, 30.1, 40.45)),
    "roman": (["sky", "poisson", "reciprocity", "dark", "persistence", "saturation", "nonlinearity", "ipc",
               "read_noise", "gain", "quantize"], {"gain": {"gain": 1.8}}, LEVELS),
}


def persistence_of(shape):
    # a constant per block keeps each block flat; a different one per block
    nb = shape[0] // BLOCK
    return np.repeat(np.linspace(3.0, 40.0, nb), BLOCK)[:, None] * np.ones((1, shape[1]))


@pytest.mark.parametrize("case", list(CASES))
def test_expectation_and_variance_match_sampled_frames(case):
    from perscli.detector.chain import forward, run_chain

    names, params, levels = CASES[case]
    model = chain_model(names, **params)
    src = flat_blocks(levels)
    pers = persistence_of(src.shape)
    fwd = forward(src, model, exptime=T, sky_rate=0.9, persistence=pers)
    chi2, dof = 0.0, 0
    for seed in (1, 2):
        r = run_chain(src, model, exptime=T, seed=seed, sky_rate=0.9, persistence=pers)
        assert r.unit == fwd.unit
        c, d = chi2_of(r.sci, fwd.mean, fwd.variance, len(levels))
        chi2, dof = chi2 + c, dof + d
    assert dof > 0
    assert p_value(chi2, dof) > 1e-4, (case, chi2, dof)


def test_the_chi2_test_can_fail():
    """The same test rejects variances that leave out IPC's kernel squared, quantisation or the gain."""
    from perscli.detector.chain import forward, run_chain

    for case, wrong in (("ipc", lambda f: f.mean),                        # Poisson variance, no kernel^2
                        ("quantize", lambda f: f.variance - 1.0 / 12.0),
                        ("gain", lambda f: f.variance * 2.5)):            # e- variance over gain, not gain^2
        names, params, levels = CASES[case]
        model = chain_model(names, **params)
        src = flat_blocks(levels)
        fwd = forward(src, model, exptime=T)
        r = run_chain(src, model, exptime=T, seed=1)
        chi2, dof = chi2_of(r.sci, fwd.mean, wrong(fwd), len(levels))
        assert p_value(chi2, dof) < 1e-6, case
    # and a wrong mean: the dark current left out
    names, params, levels = CASES["dark"]
    model = chain_model(names, **params)
    src = flat_blocks(levels)
    fwd = forward(src, model, exptime=T)
    r = run_chain(src, model, exptime=T, seed=1)
    chi2, dof = chi2_of(r.sci, fwd.mean - 0.4 * T, fwd.variance, len(levels))
    assert p_value(chi2, dof) < 1e-6


def test_forward_of_the_roman_chain_by_hand():
    """The expectation chain written out: sky, reciprocity, dark, persistence, saturation, nonlinearity,
    IPC, gain; the variance: Poisson + dark, through reciprocity, nonlinearity, IPC^2, read noise, gain^2,
    quantisation."""
    from perscli.detector.chain import forward
    from perscli.detector.effects import apply_ipc, roman_ipc_kernel
    from perscli.detector.model import load_detector_model

    model = load_detector_model("roman", ["gain.gain=1.8"])
    src = np.zeros((9, 9))
    src[4, 4] = 5.0e4
    pers = np.full(src.shape, 2.0)
    f = forward(src, model, exptime=T, sky_rate=0.5, persistence=pers)
    x = src + 0.5 * T
    alpha, t = 0.0065, T
    slope = 1 + alpha * np.log10(x / t) + alpha / np.log(10)
    v = x * slope ** 2
    x = x * (1 + alpha * np.log10(x / t))
    x = np.minimum(x + 0.015 * T + pers, 1.0e5)
    v = v + 0.015 * T
    np.testing.assert_allclose(f.fluence, x, rtol=1e-13)
    v = v * (1 + 2 * -6e-7 * x) ** 2
    x = x - 6e-7 * x * x
    k = roman_ipc_kernel()
    np.testing.assert_allclose(f.mean, apply_ipc(x, k) / 1.8, rtol=1e-13)
    np.testing.assert_allclose(f.variance, (apply_ipc(v, k ** 2) + 8.5 ** 2) / 1.8 ** 2 + 1 / 12, rtol=1e-13)
    assert f.unit == "DN" and f.sky_rate == 0.5


# -- perscli render --list-effects ----------------------------------------------------------------

def test_list_effects_needs_no_inputs():
    from perscli.detector.effects import REGISTRY

    result = invoke("render", "--list-effects")
    assert result.exit_code == 0, result.stderr
    out = result.stdout
    assert result.stderr == ""
    assert out.splitlines()[0].split() == ["EFFECT", "PARAMETER", "TYPE", "UNIT", "DEFAULT", "ALLOWED",
                                           "DESCRIPTION"]
    for name, cls in REGISTRY.items():
        assert f"\n{name} " in out
        for p in cls.schema:
            assert f" {p.name} " in out
    for text in ("e-/DN", "(0, inf)", "100000", "exact | middle | galsim", "integer [0, inf)", "(base)"):
        assert text in out, text
    # other options around it are not checked: it stops first
    assert invoke("render", "truth-that-does-not-exist.fits", "--list-effects").exit_code == 0


# -- the model in the frame, and --model FRAME.fits ---------------------------------------------

TWEAKS = ["--set", "read_noise.sigma=5.25", "--set", "gain.gain=1.7", "--set", "persistence.base=pessimistic",
          "--set", "persistence.gamma=1.05", "--set", "persistence.max_previous=1", "--set", "ipc=off",
          "--set", "saturation.full_well=8.5e4", "--set", "reciprocity.alpha=0.011", "--set", "quantize=off"]


@pytest.fixture(scope="module")
def earlier(work, truth):
    e1 = render(work / "p1.fits", truth, seed=21)
    e2 = render(work / "p2.fits", truth, "--previous", e1, mjd=MJD2, seed=22)
    return e1, e2


def read_images(path):
    with fits.open(path) as hdul:
        return {h.name: np.asarray(h.data) for h in hdul[1:] if h.is_image}


def test_model_reloads_from_the_frame_and_reproduces_it(work, truth, earlier):
    from perscli.detector.model import load_detector_model

    e1, e2 = earlier
    a = render(work / "a.fits", truth, *TWEAKS, "--previous", e1, "--previous", e2, mjd=MJD3, seed=31)
    b = render(work / "b.fits", truth, "--model", a, "--previous", e1, "--previous", e2, mjd=MJD3, seed=31)
    ia, ib = read_images(a), read_images(b)
    assert sorted(ia) == ["DRAWN", "FLUENCE", "IDEAL", "PERSIST", "SCI"]          # the default HDUs
    for name in ia:
        assert ia[name].tobytes() == ib[name].tobytes(), name
    # the model read back is the one written: every effect, its order, on/off and every parameter
    settings = [s for s in TWEAKS if s != "--set"]
    made = load_detector_model("roman", settings)
    back = load_detector_model(a)
    assert back.describe() == made.describe()
    assert [(e.name, e.enabled) for e in back.effects] == [(e.name, e.enabled) for e in made.effects]
    assert load_detector_model(b).describe() == made.describe()
    assert back.get("persistence").resolved()["source"] == "drawn"          # the default, recorded
    with fits.open(a) as hdul:
        t = Table(hdul["MODEL"].data)
        assert hdul[0].header["DETNEFF"] == 11 and hdul[0].header["DETMODEL"] == "roman"
    row = [r for r in t if r["EFFECT"] == "read_noise"][0]
    assert (row["PARAM"], row["VALUE"], row["UNIT"], bool(row["ENABLED"])) == ("sigma", "5.25", "e-", True)
    assert not [r for r in t if r["EFFECT"] == "ipc"][0]["ENABLED"]
    # max_previous=1 acted: the persistence is that of e2 alone
    only = render(work / "only_e2.fits", truth, *TWEAKS, "--previous", e2, mjd=MJD3, seed=31)
    assert read_images(only)["PERSIST"].tobytes() == ia["PERSIST"].tobytes()
    # and --set on top of a frame's model
    c = load_detector_model(a, ["read_noise.sigma=2", "ipc=on"])
    assert c.get("read_noise").params["sigma"] == 2.0 and c.enabled("ipc") and c.value("gain", "gain") == 1.7


def test_max_previous_zero_counts_every_earlier_exposure(work, truth, earlier):
    e1, e2 = earlier
    both = ["--previous", e1, "--previous", e2]
    ten = render(work / "mp10.fits", truth, *both, mjd=MJD3, seed=5)
    zero = render(work / "mp0.fits", truth, "--set", "persistence.max_previous=0", *both, mjd=MJD3, seed=5)
    one = render(work / "mp1.fits", truth, "--set", "persistence.max_previous=1", *both, mjd=MJD3, seed=5)
    p10, p0, p1 = (read_images(x)["PERSIST"].astype(np.float64) for x in (ten, zero, one))
    np.testing.assert_array_equal(p0, p10)
    assert np.all(p1 <= p0) and np.any(p1 < p0)


def test_model_from_a_frame_without_one_is_an_error(tmp_path):
    from perscli.detector.model import load_detector_model
    from perscli import PerscliError

    path = tmp_path / "plain.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(np.zeros((4, 4), np.float32), name="SCI")]).writeto(path)
    with pytest.raises(PerscliError, match="no MODEL table"):
        load_detector_model(str(path))


def test_corrupt_model_table_is_one_clear_error(tmp_path, earlier):
    from perscli import PerscliError
    from perscli.detector.model import load_detector_model

    with fits.open(earlier[0]) as hdul:
        t = Table(hdul["MODEL"].data)
    t["VALUE"][2] = "{oops"
    path = tmp_path / "bad.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.table_to_hdu(t)]).writeto(path)
    with fits.open(path, mode="update") as hdul:
        hdul[1].name = "MODEL"
    with pytest.raises(PerscliError, match="MODEL row 3: the value '{oops' of reciprocity.alpha is not valid JSON"):
        load_detector_model(str(path))


def test_saturated_fluence_and_its_persistence(work, truth, earlier):
    """The default model clips the collected charge at the full well: FLUENCE never exceeds it, IDEAL keeps
    the scene; the light drawn persists uncapped by default (GalSim's law extrapolated beyond the well), and
    with persistence.fluence_cap=well the persistence stays below F(full well) x T."""
    import math

    from perscli.detector.effects import FULL_WELL
    from perscli.detector.persistence import PersistenceModel
    from perscli.detector.settings import PRESETS

    e1, e2 = earlier
    i1, i2 = read_images(e1), read_images(e2)
    assert i1["FLUENCE"].max() == np.float32(FULL_WELL) and i1["IDEAL"].max() > 10 * FULL_WELL
    assert np.count_nonzero(i1["FLUENCE"] == np.float32(FULL_WELL)) >= 5           # the J = 15 star's core
    law = PersistenceModel(**PRESETS["typical"])
    gap = 30.0
    bound = float(law.F(np.array([FULL_WELL]))[0]) * 1000.0 * math.log((gap + T) / gap)
    assert i2["PERSIST"].max() > bound * 1.01                        # the core's light beyond the well
    capped = read_images(render(work / "p2_well.fits", truth, "--previous", e1, "--set", "persistence.fluence_cap=well",
                                mjd=MJD2, seed=22))
    assert capped["PERSIST"].max() <= bound * (1 + 1e-6)
    assert capped["PERSIST"].max() > 0.99 * bound                    # reached by the saturated core


def test_measure_noise_model_reads_the_frames_detector_model(work, truth):
    from perscli.io.frames import open_frame
    from perscli.measure.noise import noise_model

    path = render(work / "nm.fits", truth, "--set", "read_noise.sigma=3", "--set", "dark.current=0.1",
                  "--set", "gain.gain=2", seed=3)
    with open_frame(path) as frame:
        rate = float(frame.keyword("SKYRATE"))
        nm = noise_model(frame)
        assert nm.detector == "MODEL"
        sky_e = (rate + 0.1) * T
        assert nm.background == pytest.approx(sky_e / 2, rel=1e-12)
        assert nm.variance == pytest.approx((sky_e + 9.0) / 4, rel=1e-12)
        assert noise_model(frame, read_noise=5.0).variance == pytest.approx((sky_e + 25.0) / 4, rel=1e-12)
    # read noise off in the model: no read noise in the noise model
    off = render(work / "nm_off.fits", truth, "--set", "read_noise=off", "--set", "dark=off", seed=3)
    with open_frame(off) as frame:
        nm = noise_model(frame)
        assert nm.variance == pytest.approx(float(frame.keyword("SKYRATE")) * T, rel=1e-12)



def test_a_foreign_model_table_is_not_a_detector_model(tmp_path):
    """measure on another program's frame with a MODEL table of its own: the default Roman model."""
    from perscli.io.frames import open_frame
    from perscli.measure.noise import frame_detector_model

    path = tmp_path / "foreign.fits"
    table = fits.BinTableHDU.from_columns([fits.Column("NAME", "10A", array=["a"])], name="MODEL")
    sci = fits.ImageHDU(np.zeros((4, 4), np.float32), name="SCI")
    sci.header["BUNIT"] = "electron"
    fits.HDUList([fits.PrimaryHDU(), sci, table]).writeto(path)
    with open_frame(str(path)) as frame:
        model, where = frame_detector_model(frame)
    assert where == "roman" and model.value("read_noise", "sigma") == 8.5
