"""The detector chain (perscli.detector.effects): each effect does what its definition says,
in physical order, with its own random stream; detector-model YAML files and --set overrides."""

import numpy as np
import pytest

from perscli import PerscliError
from perscli.detector import effects
from perscli.detector.chain import run_chain
from perscli.detector.effects import DEFAULTS, ORDER, apply_ipc
from perscli.detector.model import DetectorModel, Effect, load_detector_model

T = 139.8


def only(*names, **params):
    """A model with just these effects on (Roman defaults, ``params`` = {name: {key: value}})."""
    effs = []
    for name in names:
        p = dict(DEFAULTS[name])
        p.update(params.get(name, {}))
        effs.append(Effect(name, p))
    return DetectorModel(effs, source="test")


def never(*args, **kw):
    raise AssertionError("must not be called")


@pytest.fixture(scope="module")
def sources():
    """A smooth field of source electrons (0 .. ~2e5) with a bright peak, 64 x 64."""
    y, x = np.mgrid[0:64, 0:64]
    img = 2.0e5 * np.exp(-((x - 30.3) ** 2 + (y - 33.7) ** 2) / (2 * 2.5 ** 2))
    img += 50.0 * (1 + np.sin(x / 5.0))
    return img


# -- run_chain, effect by effect ----------------------------------------------------------------

def test_empty_chain_is_identity(sources):
    r = run_chain(sources, DetectorModel([]), exptime=T, seed=1, sky_rate=never, persistence=never)
    assert np.array_equal(r.sci, sources) and np.array_equal(r.ideal, sources)
    assert np.array_equal(r.fluence, sources)
    assert r.unit == "electron" and r.persistence is None and r.sky_rate == 0.0
    assert r.sci is not sources                      # the input is not modified in place


def test_all_effects_off_is_identity(sources):
    model = load_detector_model("roman", [f"{name}=off" for name in ORDER])
    r = run_chain(sources, model, exptime=T, seed=1, sky_rate=never, persistence=never)
    assert np.array_equal(r.sci, sources)
    assert r.unit == "electron"


def test_sky_auto_adds_rate_times_exptime(sources):
    r = run_chain(sources, only("sky"), exptime=T, seed=1, sky_rate=lambda: 1.25)
    np.testing.assert_allclose(r.sci - sources, 1.25 * T, rtol=1e-12)
    assert r.sky_rate == 1.25
    # the ideal frame holds the sky too
    np.testing.assert_allclose(r.ideal, sources + 1.25 * T, rtol=1e-12)


def test_sky_level_number_overrides_auto(sources):
    r = run_chain(sources, only("sky", sky={"level": 2.0}), exptime=T, seed=1, sky_rate=never)
    np.testing.assert_allclose(r.sci - sources, 2.0 * T, rtol=1e-12)
    assert r.sky_rate == 2.0
    r = run_chain(sources, only("sky"), exptime=T, seed=1, sky_rate=3.5)      # a plain number works too
    np.testing.assert_allclose(r.sci - sources, 3.5 * T, rtol=1e-12)


def test_sky_off_does_not_ask_for_the_sky(sources):
    model = load_detector_model("roman", ["sky=off", "persistence=off"])
    r = run_chain(sources, model, exptime=T, seed=1, sky_rate=never)
    assert r.sky_rate == 0.0


def test_poisson_integers_with_variance_equal_to_mean():
    lam = np.full((200, 200), 37.5)
    r = run_chain(lam, only("poisson"), exptime=T, seed=3)
    assert np.array_equal(r.sci, np.round(r.sci))
    n = lam.size
    assert abs(r.sci.mean() - 37.5) < 5 * np.sqrt(37.5 / n)
    assert abs(r.sci.var() / 37.5 - 1) < 5 * np.sqrt(2.0 / n)
    assert np.array_equal(r.ideal, lam)             # IDEAL is the expectation, before the noise


def test_poisson_clips_negative_expectations():
    img = np.array([[-5.0, 0.0], [-1e-9, 0.0]])
    r = run_chain(img, only("poisson"), exptime=T, seed=1)
    assert np.array_equal(r.sci, np.zeros((2, 2)))


def test_poisson_ideal_is_sources_plus_sky(sources):
    r = run_chain(sources, only("sky", "poisson", "dark", "read_noise"), exptime=T, seed=4, sky_rate=1.0)
    np.testing.assert_allclose(r.ideal, sources + T, rtol=1e-12)
    # residuals normalised by the expected noise are unit normal
    z = (r.sci - r.ideal - DEFAULTS["dark"]["current"] * T) / np.sqrt(r.ideal + 8.5 ** 2 + 0.015 * T)
    assert abs(z.mean()) < 5 / 64 and abs(z.std() - 1) < 0.05


@pytest.mark.parametrize("alpha, base_flux", [(0.0065, 1.0), (0.05, 3.0)])
def test_reciprocity_formula(sources, alpha, base_flux):
    img = sources.copy()
    img[0, :3] = [0.0, -4.0, 1e-3]
    r = run_chain(img, only("reciprocity", reciprocity={"alpha": alpha, "base_flux": base_flux}),
                  exptime=T, seed=1)
    pos = img > 0
    expect = img.copy()
    expect[pos] = img[pos] * (1 + alpha * np.log10(img[pos] / (base_flux * T)))
    np.testing.assert_allclose(r.sci, expect, rtol=1e-13)
    assert r.sci[0, 0] == 0.0 and r.sci[0, 1] == -4.0           # zero and negative pixels left alone
    # the bright peak gains, faint pixels (below base_flux * t) lose
    assert r.sci.max() > img.max() and r.sci[0, 2] < img[0, 2]


def test_dark_adds_poisson_current():
    img = np.zeros((200, 200))
    r = run_chain(img, only("dark", dark={"current": 0.2}), exptime=T, seed=9)
    mean = 0.2 * T
    assert np.array_equal(r.sci, np.round(r.sci)) and r.sci.min() >= 0
    n = img.size
    assert abs(r.sci.mean() - mean) < 5 * np.sqrt(mean / n)
    assert abs(r.sci.var() / mean - 1) < 5 * np.sqrt(2.0 / n)
    assert np.array_equal(r.ideal, img)              # dark is not part of IDEAL


def test_persistence_added_and_part_of_fluence(sources):
    pers = np.linspace(0, 30, sources.size).reshape(sources.shape)
    calls = []

    def persistence():
        calls.append(1)
        return pers

    model = only("persistence", "nonlinearity")
    r = run_chain(sources, model, exptime=T, seed=1, persistence=persistence)
    assert calls == [1]
    np.testing.assert_array_equal(r.persistence, pers)
    np.testing.assert_allclose(r.fluence, sources + pers, rtol=1e-14)       # charge before nonlinearity
    beta = DEFAULTS["nonlinearity"]["beta"]
    np.testing.assert_allclose(r.sci, r.fluence + beta * r.fluence ** 2, rtol=1e-13)
    # the effect switched off: the callable is not even called
    off = DetectorModel([Effect("persistence", dict(DEFAULTS["persistence"]), enabled=False)])
    r = run_chain(sources, off, exptime=T, seed=1, persistence=never)
    assert r.persistence is None and np.array_equal(r.sci, sources)


@pytest.mark.parametrize("beta", [-6.0e-7, -2.0e-6, 1.0e-7])
def test_nonlinearity_formula_and_fluence_is_before_it(sources, beta):
    r = run_chain(sources, only("sky", "nonlinearity", nonlinearity={"beta": beta}), exptime=T, seed=1,
                  sky_rate=0.5)
    x = sources + 0.5 * T
    np.testing.assert_allclose(r.fluence, x, rtol=1e-14)
    np.testing.assert_allclose(r.sci, x + beta * x * x, rtol=1e-13)


def test_fluence_excludes_everything_after_persistence(sources):
    model = load_detector_model("roman", ["poisson=off", "dark=off"])
    r = run_chain(sources, model, exptime=T, seed=1, sky_rate=1.0)
    x = sources + T
    x = x * (1 + 0.0065 * np.log10(x / T))
    x = np.minimum(x, effects.FULL_WELL)
    assert np.count_nonzero(x == effects.FULL_WELL) > 5             # the peak is saturated
    np.testing.assert_allclose(r.fluence, x, rtol=1e-13)         # sky + reciprocity + saturation, nothing later
    assert not np.allclose(r.sci, r.fluence)


def _galsim_ipc(img):
    import galsim
    import galsim.roman

    im = galsim.Image(np.array(img, dtype=np.float64))
    im.applyIPC(galsim.roman.ipc_kernel, edge_treatment="extend")
    return im.array


def test_ipc_roman_kernel_is_galsims():
    import galsim.roman

    np.testing.assert_array_equal(effects.roman_ipc_kernel(), galsim.roman.ipc_kernel.array)
    assert abs(effects.roman_ipc_kernel().sum() - 1) < 1e-12


def test_ipc_single_pixel_spreads_over_3x3_conserving_charge():
    img = np.zeros((9, 11))
    img[4, 5] = 1.0e4
    r = run_chain(img, only("ipc"), exptime=T, seed=1)
    k = effects.roman_ipc_kernel()
    # GalSim's convention: kernel[j, i] is what a pixel receives from its neighbour at (i-1, j-1),
    # so a lone bright pixel shows the kernel flipped
    np.testing.assert_allclose(r.sci[3:6, 4:7] / 1.0e4, k[::-1, ::-1], rtol=1e-12)
    assert np.count_nonzero(r.sci) == 9
    assert abs(r.sci.sum() - 1.0e4) < 1e-8
    np.testing.assert_allclose(r.fluence, img)                  # IPC acts after the charge is collected
    # the Roman kernel is not symmetric: the orientation matters
    assert abs(r.sci[4, 4] - r.sci[4, 6]) > 1e-3 * 1.0e4


def test_ipc_custom_kernel_orientation():
    """A one-sided kernel: each pixel receives 10 % of its right-hand neighbour's signal."""
    kernel = [[0.0, 0.0, 0.0], [0.0, 0.9, 0.1], [0.0, 0.0, 0.0]]
    img = np.zeros((5, 5))
    img[2, 2] = 100.0
    r = run_chain(img, only("ipc", ipc={"kernel": kernel}), exptime=T, seed=1)
    assert r.sci[2, 2] == pytest.approx(90.0) and r.sci[2, 1] == pytest.approx(10.0)
    assert r.sci.sum() == pytest.approx(100.0)


def test_ipc_matches_galsim_apply_ipc(sources):
    r = run_chain(sources, only("ipc"), exptime=T, seed=1)
    np.testing.assert_allclose(r.sci, _galsim_ipc(sources), rtol=1e-12)
    # a uniform frame: unchanged inside; the edges receive nothing from beyond (GalSim's 'extend')
    img = np.full((6, 7), 123.0)
    out = apply_ipc(img, effects.roman_ipc_kernel())
    np.testing.assert_allclose(out[1:-1, 1:-1], 123.0, rtol=1e-13)
    np.testing.assert_allclose(out, _galsim_ipc(img), rtol=1e-13)


def test_read_noise_gaussian_sigma():
    img = np.full((200, 200), 500.0)
    r = run_chain(img, only("read_noise", read_noise={"sigma": 5.0}), exptime=T, seed=2)
    d = r.sci - img
    n = img.size
    assert abs(d.mean()) < 5 * 5.0 / np.sqrt(n)
    assert abs(d.std() / 5.0 - 1) < 5 / np.sqrt(2 * n)
    assert not np.array_equal(d, np.round(d))                     # not quantised
    # fourth moment of a Gaussian: 3 sigma^4
    assert abs(np.mean(d ** 4) / (3 * 5.0 ** 4) - 1) < 0.05


def test_gain_divides_and_sets_dn(sources):
    r = run_chain(sources, only("gain", gain={"gain": 2.5}), exptime=T, seed=1)
    np.testing.assert_allclose(r.sci, sources / 2.5, rtol=1e-15)
    assert r.unit == "DN"
    np.testing.assert_array_equal(r.ideal, sources)            # IDEAL stays in electrons
    np.testing.assert_array_equal(r.fluence, sources)


def test_quantize_rounds_to_nearest_integer(sources):
    noisy = run_chain(sources, only("read_noise", "gain", gain={"gain": 1.7}), exptime=T, seed=5)
    q = run_chain(sources, only("read_noise", "gain", "quantize", gain={"gain": 1.7}), exptime=T, seed=5)
    assert np.array_equal(q.sci, np.round(q.sci))
    assert np.all(np.abs(q.sci - noisy.sci) <= 0.5)
    np.testing.assert_array_equal(q.sci, np.round(noisy.sci))
    assert q.unit == "DN"


def test_default_chain_without_noise_is_the_composition_in_physical_order(sources):
    """sky -> reciprocity -> saturation -> nonlinearity -> ipc -> gain -> quantize, written out by hand."""
    model = load_detector_model("roman", ["poisson=off", "dark=off", "read_noise=off", "gain.gain=1.6",
                                          "saturation.full_well=1.5e5"])
    r = run_chain(sources, model, exptime=T, seed=1, sky_rate=0.8)
    x = sources + 0.8 * T
    x = x * (1 + 0.0065 * np.log10(x / T))
    x = np.minimum(x, 1.5e5)
    x = x - 6.0e-7 * x * x
    x = apply_ipc(x, effects.roman_ipc_kernel())
    np.testing.assert_array_equal(r.sci, np.round(x / 1.6))
    assert r.unit == "DN" and r.sky_rate == 0.8


# -- random streams ------------------------------------------------------------------------------

def test_same_seed_same_frame_different_seed_different(sources):
    model = load_detector_model("roman", ["persistence=off"])
    a = run_chain(sources, model, exptime=T, seed=11, sky_rate=1.0)
    b = run_chain(sources, model, exptime=T, seed=11, sky_rate=1.0)
    c = run_chain(sources, model, exptime=T, seed=12, sky_rate=1.0)
    np.testing.assert_array_equal(a.sci, b.sci)
    assert np.mean(a.sci != c.sci) > 0.9


def test_each_effect_has_its_own_stream(sources):
    """Switching dark on adds exactly its own realisation; the Poisson and read noise do not change."""
    base = only("sky", "poisson", "read_noise")
    with_dark = only("sky", "poisson", "dark", "read_noise", dark={"current": 0.1})
    a = run_chain(sources, base, exptime=T, seed=21, sky_rate=1.0)
    b = run_chain(sources, with_dark, exptime=T, seed=21, sky_rate=1.0)
    d = b.sci - a.sci
    np.testing.assert_allclose(d, np.round(d), atol=1e-6)          # an integer Poisson draw per pixel
    mean = 0.1 * T
    assert d.min() >= -1e-6
    assert abs(d.mean() - mean) < 5 * np.sqrt(mean / d.size)
    assert abs(d.var() / mean - 1) < 5 * np.sqrt(2.0 / d.size)
    # the same with read noise off: SCI(dark) - SCI(no dark) is the same realisation
    a2 = run_chain(sources, only("sky", "poisson"), exptime=T, seed=21, sky_rate=1.0)
    b2 = run_chain(sources, only("sky", "poisson", "dark", dark={"current": 0.1}), exptime=T, seed=21,
                   sky_rate=1.0)
    np.testing.assert_allclose(b2.sci - a2.sci, d, atol=1e-6)


def test_persistence_on_or_off_leaves_the_noise_alone(sources):
    pers = np.zeros_like(sources)
    pers[10:20, 10:20] = 7.0
    model = load_detector_model("roman", ["nonlinearity=off", "ipc=off", "quantize=off", "gain.gain=2"])
    a = run_chain(sources, model, exptime=T, seed=5, sky_rate=1.0, persistence=lambda: pers)
    model_off = load_detector_model("roman", ["nonlinearity=off", "ipc=off", "quantize=off", "gain.gain=2",
                                              "persistence=off"])
    b = run_chain(sources, model_off, exptime=T, seed=5, sky_rate=1.0, persistence=never)
    np.testing.assert_allclose(a.sci - b.sci, pers / 2.0, atol=1e-9)


# -- detector models ------------------------------------------------------------------------------

def write(tmp_path, text, name="model.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_default_model_is_galsims_roman_chain():
    import galsim.roman as roman

    for spec in (None, "roman", "default"):
        m = load_detector_model(spec)
        # not in GalSim's Roman chain: a bias offset, brighter-fatter, correlated read noise
        assert [e.name for e in m.effects] == [n for n in ORDER
                                               if n not in ("offset", "brighter_fatter", "correlated_read_noise")]
        assert all(e.enabled for e in m.effects)
        assert m.source == "roman"
    m = load_detector_model()
    assert m.get("reciprocity").params["alpha"] == roman.reciprocity_alpha
    assert m.get("dark").params["current"] == roman.dark_current
    assert m.get("nonlinearity").params["beta"] == roman.nonlinearity_beta
    assert m.get("read_noise").params["sigma"] == roman.read_noise
    assert m.get("gain").params["gain"] == roman.gain
    # each call is a fresh copy: changing one does not change the defaults
    m.get("dark").params["current"] = 99.0
    assert load_detector_model().get("dark").params["current"] == roman.dark_current
    assert DEFAULTS["dark"]["current"] == roman.dark_current


def test_yaml_list_in_physical_order(tmp_path):
    path = write(tmp_path, "effects:\n  - sky: {level: 1.5}\n  - poisson\n  - dark: {current: 0.1}\n"
                           "  - read_noise: {sigma: 4}\n  - quantize: {}\n")
    m = load_detector_model(path)
    assert [e.name for e in m.effects] == ["sky", "poisson", "dark", "read_noise", "quantize"]
    assert m.get("sky").params == {"level": 1.5}
    assert m.get("read_noise").params == {"sigma": 4}
    assert not m.enabled("ipc") and not m.enabled("gain") and m.get("ipc") is None
    assert m.source == path
    # the chain follows the file: no gain, so electrons
    r = run_chain(np.zeros((4, 4)), m, exptime=T, seed=1, sky_rate=never)
    assert r.unit == "electron" and r.sky_rate == 1.5


def test_sample_detector_model_is_the_default_chain():
    from conftest import SAMPLE_DATA

    path = SAMPLE_DATA / "roman_detector.yaml"
    if not path.exists():
        pytest.skip("sample_data/roman_detector.yaml not present")
    m = load_detector_model(str(path))
    assert m.describe() == load_detector_model("roman").describe()


def test_yaml_mapping_form_and_defaults_for_missing_parameters(tmp_path):
    path = write(tmp_path, "reciprocity: {alpha: 0.01}\nnonlinearity:\ngain: {gain: 2}\n")
    m = load_detector_model(path)
    assert [e.name for e in m.effects] == ["reciprocity", "nonlinearity", "gain"]
    assert m.get("reciprocity").params == {"alpha": 0.01, "base_flux": 1.0}
    assert m.get("nonlinearity").params == {"beta": -6.0e-7}


def test_yaml_enabled_false_is_respected(tmp_path):
    path = write(tmp_path, "effects:\n  - sky: {level: 1.0}\n  - dark: {current: 5, enabled: false}\n"
                           "  - gain: {gain: 2, enabled: true}\n")
    m = load_detector_model(path)
    assert not m.enabled("dark") and m.get("dark") is not None and m.get("dark").params == {"current": 5}
    assert m.enabled("gain")
    r = run_chain(np.zeros((8, 8)), m, exptime=10.0, seed=1)
    np.testing.assert_array_equal(r.sci, np.full((8, 8), 5.0))       # 1.0 * 10 / 2, no dark
    # described as off for the provenance
    assert ("dark", False, {"current": 5}) in m.describe()


@pytest.mark.parametrize("text, needle", [
    ("effects:\n  - dark\n  - sky\n", "physical order"),
    ("effects:\n  - ipc\n  - nonlinearity\n", "physical order"),
    ("gain: {}\nread_noise: {}\n", "physical order"),
    ("effects:\n  - sky\n  - blur: {}\n", "unknown effect 'blur'"),
    ("effects:\n  - sky\n  - sky\n", "listed twice"),
    ("effects:\n  - read_noise: {sigma: 3, rms: 2}\n", "unknown parameter(s) rms"),
    ("effects:\n  - read_noise: {sigma: -1}\n", "must not be negative"),
    ("effects:\n  - read_noise: {sigma: lots}\n", "must be a finite number"),
    ("effects:\n  - gain: {gain: 0}\n", "must be positive"),
    ("effects:\n  - dark: {current: .nan}\n", "finite number"),
    ("effects:\n  - dark: {enabled: maybe}\n", "enabled must be true or false"),
    ("effects:\n  - ipc: {kernel: [[1, 0], [0, 1]]}\n", "3x3"),
    ("effects:\n  - ipc: {kernel: galsim}\n", "3x3"),
    ("effects:\n  - persistence: {base: awful}\n", "base must be one of"),
    ("effects:\n  - persistence: {Q: 1}\n", "unknown parameter(s) Q for effect 'persistence'"),
    ("effects:\n  - {sky: {}, dark: {}}\n", "one-key mapping"),
    ("effects: 3\n", "expected 'effects:'"),
    ("effects:\n  - sky: [\n", "not valid YAML"),
])
def test_bad_yaml_models_rejected(tmp_path, text, needle):
    path = write(tmp_path, text)
    with pytest.raises(PerscliError) as err:
        load_detector_model(path)
    assert needle in str(err.value)
    assert path in str(err.value)


def test_missing_model_file(tmp_path):
    with pytest.raises(PerscliError, match="not found"):
        load_detector_model(str(tmp_path / "nope.yaml"))


def test_overrides_set_parameters_and_switch_effects():
    m = load_detector_model("roman", ["read_noise.sigma=5", "ipc=off", "sky.level=0.25", "gain.gain=2.5"])
    assert m.get("read_noise").params["sigma"] == 5
    assert not m.enabled("ipc")
    assert m.get("sky").params["level"] == 0.25
    assert m.get("gain").params["gain"] == 2.5
    m = load_detector_model("roman", ["dark=off", "dark=on", "quantize=false", "quantize=TRUE"])
    assert m.enabled("dark") and m.enabled("quantize")
    m = load_detector_model("roman", ["ipc.kernel=[[0,0,0],[0,1,0],[0,0,0]]"])
    assert m.get("ipc").params["kernel"] == [[0, 0, 0], [0, 1, 0], [0, 0, 0]]
    m = load_detector_model("roman", ["persistence.base=pessimistic", "persistence.gamma=1.1"])
    pm = m.persistence_model()
    assert pm.A == 0.086 and pm.gamma == 1.1 and pm.x0 == 1.37e5



def test_override_accepts_scientific_notation_without_a_point():
    m = load_detector_model("roman", ["nonlinearity.beta=-6e-7", "dark.current=2e-2"])
    assert m.get("nonlinearity").params["beta"] == -6e-7
    assert m.get("dark").params["current"] == 0.02


def test_yaml_accepts_scientific_notation_without_a_point(tmp_path):
    m = load_detector_model(write(tmp_path, "effects:\n  - nonlinearity: {beta: -6e-7}\n"))
    assert m.get("nonlinearity").params["beta"] == -6e-7


def test_override_accepts_scientific_notation_with_a_point():
    m = load_detector_model("roman", ["nonlinearity.beta=-6.0e-7", "dark.current=2.0e-2"])
    assert m.get("nonlinearity").params["beta"] == -6e-7
    assert m.get("dark").params["current"] == 0.02


def test_override_adds_a_missing_effect_in_its_place(tmp_path):
    path = write(tmp_path, "effects:\n  - sky: {level: 1}\n  - gain: {gain: 2}\n")
    m = load_detector_model(path, ["read_noise.sigma=3", "ipc=on"])
    assert [e.name for e in m.effects] == ["sky", "ipc", "read_noise", "gain"]
    assert m.enabled("read_noise") and m.enabled("ipc")
    assert m.get("ipc").params == DEFAULTS["ipc"]
    # switching off an effect the file does not list keeps it off
    m = load_detector_model(path, ["dark=off"])
    assert not m.enabled("dark")


def test_override_of_a_disabled_parameter_enables_the_effect(tmp_path):
    path = write(tmp_path, "effects:\n  - read_noise: {sigma: 2, enabled: false}\n")
    m = load_detector_model(path, ["read_noise.sigma=4"])
    assert m.enabled("read_noise") and m.get("read_noise").params["sigma"] == 4


@pytest.mark.parametrize("text, needle", [
    ("blur=off", "unknown effect 'blur'"),
    ("blur.size=3", "unknown effect 'blur'"),
    ("read_noise.rms=3", "unknown parameter(s) rms"),
    ("read_noise", "EFFECT.KEY=VALUE"),
    ("dark=maybe", "dark=on or dark=off"),
    ("gain.gain=-1", "must be positive"),
    ("gain.gain=0", "must be positive"),
    ("read_noise.sigma=abc", "finite number"),
    ("sky.level=-2", "must not be negative"),
    ("ipc.kernel=[1,2,3]", "3x3"),
    ("persistence.base=awful", "base must be one of"),
    ("persistence.bogus=1", "unknown parameter(s) bogus for effect 'persistence'"),
])
def test_bad_overrides_rejected(text, needle):
    with pytest.raises(PerscliError) as err:
        load_detector_model("roman", [text])
    assert needle in str(err.value)


def test_persistence_model_of_the_default_chain_is_typical():
    from perscli.detector.settings import PRESETS

    pm = load_detector_model().persistence_model()
    assert pm.kind == "fermi"
    for key, value in PRESETS["typical"].items():
        assert getattr(pm, key) == value


def test_ipc_kernel_is_ndimage_correlate_bit_for_bit():
    """The compiled 3x3 correlation (perscli._kernels.correlate3x3) is scipy.ndimage.correlate's, bit for bit:
    zero outside, weights of at most DBL_EPSILON left out, NaN carried, a stack of planes each on its own."""
    from scipy import ndimage

    from perscli.detector.effects import apply_ipc, roman_ipc_kernel

    rng = np.random.default_rng(5)
    kernels = [roman_ipc_kernel(), rng.normal(size=(3, 3)), np.array([[0, 0.01, 0], [0.01, 0.96, 0.01], [0, 0.01, 0]]),
               np.array([[1e-17, 0.2, 0.0], [0.3, 0.5, 0.0], [0.0, 0.0, -0.1]])]
    for kernel in kernels:
        for shape in [(1, 1), (1, 5), (5, 1), (2, 2), (3, 3), (7, 11), (64, 130), (3, 6, 6)]:
            x = rng.normal(size=shape) * 1e4
            if x.size > 30:
                x.flat[::17] = np.nan
            ref = ndimage.correlate(x, kernel if x.ndim == 2 else kernel[None], mode="constant", cval=0.0)
            np.testing.assert_array_equal(apply_ipc(x, kernel), ref)
    # float32 in: correlated in float64, as the chain's images are
    x = rng.normal(size=(9, 9)).astype(np.float32)
    np.testing.assert_array_equal(apply_ipc(x, kernels[0]),
                                  ndimage.correlate(x.astype(np.float64), kernels[0], mode="constant"))


def test_stamps_are_added_as_numpy_adds_their_slices_bit_for_bit():
    """render's compiled stamp adder (perscli._kernels.add_stamps through render.exposure.add_stamp_run) gives
    the bits of the numpy loop it replaced: each stamp rolled by n/2, times its flux, its slice added in
    order, clipped at every edge, the stars also into their own image (or only there)."""
    from perscli.render.exposure import StampRun, add_stamp_run

    rng = np.random.default_rng(3)
    bounds = (5, 94, -3, 66)
    shape = (bounds[3] - bounds[2] + 1, bounds[1] - bounds[0] + 1)
    stamps = (rng.normal(size=(4, 8, 8)), rng.normal(size=(3, 32, 32)), rng.normal(size=(2, 2, 2)))
    n_obj = 300
    group = rng.integers(0, 3, n_obj)
    slot = np.array([rng.integers(0, len(stamps[g])) for g in group])
    x0 = rng.integers(bounds[0] - 40, bounds[1] + 5, n_obj)
    y0 = rng.integers(bounds[2] - 40, bounds[3] + 5, n_obj)
    index = rng.permutation(n_obj)
    is_star = rng.integers(0, 2, n_obj).astype(bool)
    run = StampRun(index, x0, y0, rng.uniform(1, 1e4, n_obj), group, slot, stamps)
    base = rng.normal(size=shape)
    image, stars, only = base.copy(), base.copy(), base.copy()
    add_stamp_run(run, image, bounds, stars, is_star)
    add_stamp_run(run, None, bounds, only, is_star)
    want, want_stars = base.copy(), base.copy()
    for o in range(n_obj):
        st = stamps[group[o]][slot[o]]
        n = st.shape[0]
        st = np.roll(st, (n // 2, n // 2), axis=(0, 1)) * run.flux[o]
        a0, a1 = max(x0[o], bounds[0]), min(x0[o] + n, bounds[1] + 1)
        b0, b1 = max(y0[o], bounds[2]), min(y0[o] + n, bounds[3] + 1)
        if a0 < a1 and b0 < b1:
            part = st[b0 - y0[o]:b1 - y0[o], a0 - x0[o]:a1 - x0[o]]
            want[b0 - bounds[2]:b1 - bounds[2], a0 - bounds[0]:a1 - bounds[0]] += part
            if is_star[index[o]]:
                want_stars[b0 - bounds[2]:b1 - bounds[2], a0 - bounds[0]:a1 - bounds[0]] += part
    assert np.array_equal(image, want) and not np.array_equal(image, base)
    assert np.array_equal(stars, want_stars) and np.array_equal(only, want_stars)
    with pytest.raises(ValueError, match="group or slot"):
        add_stamp_run(run._replace(slot=slot + 5), image, bounds)


def test_inactive_blocks_are_blanked_as_the_pixel_mask_blanks_them():
    """blank_inactive (one slice per block left out) leaves NaN exactly where active_pixels is False, for
    images that start and end inside blocks."""
    from perscli.detector.blocks import active_pixels, blank_inactive, block_grid

    rng = np.random.default_rng(1)
    for origin, shape in [((1, 1), (300, 200)), ((37, 100), (129, 257)), ((4000, 3990), (89, 99))]:
        grid = block_grid(origin, shape)
        active = rng.random((grid[2], grid[3])) < 0.5
        want = rng.normal(size=shape)
        got = blank_inactive(want.copy(), active, origin)
        want[~active_pixels(active, origin, shape)] = np.nan
        np.testing.assert_array_equal(got, want)
        assert np.isnan(got).any() and np.isfinite(got).any()


def test_a_block_stack_gathers_and_scatters_each_block_as_its_slices():
    """BlockStack.gather/scatter (whole blocks in one gather, the cut ones one at a time) put each block's
    pixels where its own slices of the area say, ``fill`` beyond the area, in the dtype asked for."""
    from perscli.detector.blocks import BlockStack, block_grid

    rng = np.random.default_rng(0)
    for origin, shape in [((1, 1), (256, 192)), ((1, 1), (250, 189)), ((33, 65), (100, 70))]:
        grid = block_grid(origin, shape)
        stack = BlockStack.of(rng.random((grid[2], grid[3])) < 0.5, origin, shape)
        image = rng.normal(size=shape)
        for fill, dtype in [(np.nan, np.float64), (0.0, np.float32)]:
            got = stack.gather(image, fill=fill, dtype=dtype)
            want = np.full(got.shape, fill, dtype=dtype)
            back = np.full(shape, fill, dtype=dtype)
            for k in range(len(stack)):
                rows, cols = stack._place(k)
                want[k, :stack.h[k], :stack.w[k]] = image[rows, cols]
                back[rows, cols] = want[k, :stack.h[k], :stack.w[k]]
            np.testing.assert_array_equal(got, want)
            np.testing.assert_array_equal(stack.scatter(got, fill=fill, dtype=dtype), back)
        # a part of the area (a frame inside its simulation area): as if padded with ``fill`` to the area
        for at, part_shape in [((3, 5), (shape[0] - 7, shape[1] - 9)), ((0, 0), shape), ((40, 33), (20, 20))]:
            part = rng.normal(size=part_shape).astype(np.float32)
            padded = np.zeros(shape, dtype=np.float32)
            padded[at[0]:at[0] + part_shape[0], at[1]:at[1] + part_shape[1]] = part
            np.testing.assert_array_equal(stack.gather(part, fill=0.0, dtype=np.float32, at=at),
                                          stack.gather(padded, fill=0.0, dtype=np.float32))


def test_reciprocity_moments_are_its_expectation_and_variance():
    """forward's one-pass moments equal the effect's own expectation and variance (shared logarithm)."""
    from perscli.detector.blocks import ChainContext
    from perscli.detector.effects import REGISTRY

    rng = np.random.default_rng(2)
    mean = rng.normal(size=(40, 40)) * 1e3 + 200.0
    mean[0, :5] = [0.0, -1.0, 1e-300, 1e6, np.inf]
    var = rng.uniform(1, 10, size=mean.shape)
    ctx = ChainContext(exptime=139.8, seed=0)
    step = REGISTRY["reciprocity"]({"alpha": 0.0065, "base_flux": 1.0})
    m, v = step.moments(mean.copy(), var.copy(), ctx)
    np.testing.assert_array_equal(m, step.expectation(mean.copy(), ctx))
    np.testing.assert_array_equal(v, step.variance(mean.copy(), var.copy(), ctx))


def test_forward_with_the_charge_stage_kept_is_the_same_bit_for_bit():
    """diagnose keeps the chain's charge stage between evaluations that change only the readout: the result
    must be that of a fresh forward whatever changes, and a changed charge-stage parameter must not hit."""
    import dataclasses

    from perscli.detector.chain import ChargeCache, forward
    from perscli.detector.model import default_model
    from perscli.diagnose.likelihood import with_effect

    rng = np.random.default_rng(3)
    ideal = rng.uniform(0, 2e5, size=(30, 40))
    pers = rng.uniform(0, 50, size=ideal.shape)
    base = with_effect(default_model(), "sky", enabled=False)
    models = [base,
              with_effect(base, "gain", {"gain": 1.7}),                     # readout only: a hit
              with_effect(base, "nonlinearity", {"beta": -2e-6}),
              with_effect(base, "reciprocity", {"alpha": 0.01}),           # charge stage: a miss
              with_effect(base, "dark", {"current": 0.2}),
              with_effect(base, "saturation", {"full_well": 1.5e5}),
              base]
    cache = ChargeCache(keep=2)
    for model in models:
        fresh = forward(ideal, model, exptime=139.8, persistence=pers)
        kept = forward(ideal, model, exptime=139.8, persistence=pers, cache=cache, key="exposure 0")
        for f in dataclasses.fields(fresh):
            a, b = getattr(fresh, f.name), getattr(kept, f.name)
            if isinstance(a, np.ndarray):
                np.testing.assert_array_equal(a, b)
            else:
                assert a == b
    # what the cache holds cannot be changed through a result
    kept = forward(ideal, base, exptime=139.8, persistence=pers, cache=cache, key="exposure 0")
    with pytest.raises(ValueError):
        kept.fluence[0, 0] = 0.0
    kept.mean[0, 0] = -1.0                                             # the caller's own copy
    again = forward(ideal, base, exptime=139.8, persistence=pers, cache=cache, key="exposure 0")
    assert again.mean[0, 0] != -1.0


def test_a_readout_change_reuses_the_charge_stage(monkeypatch):
    from perscli.detector.chain import ChargeCache, forward
    from perscli.detector.effects import REGISTRY
    from perscli.detector.model import default_model
    from perscli.diagnose.likelihood import with_effect

    ideal = np.full((8, 8), 1e4)
    base = with_effect(default_model(), "sky", enabled=False)
    cache = ChargeCache()
    forward(ideal, base, exptime=139.8, cache=cache, key=0)

    def fail(*a, **k):
        raise AssertionError("the charge stage ran again")

    monkeypatch.setattr(REGISTRY["reciprocity"], "moments", fail)
    forward(ideal, with_effect(base, "gain", {"gain": 2.0}), exptime=139.8, cache=cache, key=0)
    with pytest.raises(AssertionError, match="ran again"):
        forward(ideal, with_effect(base, "dark", {"current": 1.0}), exptime=139.8, cache=cache, key=0)
    with pytest.raises(AssertionError, match="ran again"):
        forward(ideal, base, exptime=100.0, cache=cache, key=0)
