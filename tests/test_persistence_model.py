"""The persistence law itself: presets, branches, YAML files, overrides, time integral."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy import integrate

from perscli import PerscliError, _kernels
from perscli.detector.model import load_persistence_model as load_model
from perscli.detector.persistence import PersistenceModel, accumulate, time_factor
from perscli.detector.settings import GALSIM_LINEAR_COEFFICIENTS, PRESETS
from perscli.io.checksum import ones_complement_add


def paper_F(x, A, x0, dx, alpha, half_well, **_):
    """The paper's law written out independently: Fermi above half_well, linear below."""
    x = np.asarray(x, dtype=float)
    fermi = lambda v: A / (np.exp(-(v - x0) / dx) + 1.0) * (v / x0) ** alpha  # noqa: E731
    with np.errstate(invalid="ignore"):
        return np.where(x > half_well, fermi(x), np.where(x > 0, fermi(half_well) * x / half_well, 0.0))


@pytest.mark.parametrize("name", ["typical", "pessimistic"])
def test_presets_are_the_papers_table_1(name):
    model = load_model(name)
    expected = {"typical": (0.017, 6.0e4, 5.0e4, 0.045, 1.0), "pessimistic": (0.086, 1.37e5, 2.6e4, 0.02, 1.0)}
    assert (model.A, model.x0, model.dx, model.alpha, model.gamma) == expected[name]
    assert model.half_well == 5e4


def test_branches_match_the_papers_formula():
    x = np.array([-1e3, 0.0, 1.0, 2.5e4, 5e4, 5e4 + 1e-6, 6e4, 1e5, 1e6])
    for name in PRESETS:
        model = load_model(name)
        np.testing.assert_allclose(model.F(x), paper_F(x, **PRESETS[name]), rtol=1e-14, atol=0)
    # continuous at half_well, zero at and below zero fluence
    m = load_model("typical")
    assert m.F([5e4])[0] == pytest.approx(m.F([5e4 * (1 + 1e-12)])[0], rel=1e-9)
    assert m.F([0.0, -5.0]).tolist() == [0.0, 0.0]


def test_saturated_pixel_leaves_dozens_of_electrons_in_the_next_exposure():
    # the paper: saturated pixels give "persistence signals of several dozens of electrons in a
    # subsequent 140s exposure"; Roman's cadence leaves a ~30 s gap before the next exposure
    m = load_model("typical")
    charge = m.F([1.2e5, 2e5]) * time_factor(30.0, 30.0 + 139.8, 1.0)
    assert np.all((charge > 10) & (charge < 100))


def test_compiled_kernel_equals_numpy_law_for_every_byte_order():
    rng = np.random.default_rng(3)
    x = 10 ** rng.uniform(-1, 6, 5000)
    x[:3] = [-1.0, 0.0, np.nan]
    for name in ("typical", "pessimistic"):
        model = load_model(name)
        expected = model.F(np.nan_to_num(x, nan=0.0)) * 2.5
        for dtype in ("<f8", ">f8", "<f4", ">f4"):
            xv = x.astype(dtype)
            acc = np.zeros((1, x.size))
            bad, datasum = accumulate(xv, acc, [2.5], model)
            ref = model.F(np.nan_to_num(xv.astype(float), nan=0.0)) * 2.5
            np.testing.assert_allclose(acc[0], ref, rtol=1e-13, atol=0)
            assert bad == 1
            # the DATASUM gathered on the way is that of the values stored big-endian
            assert datasum == _kernels.datasum(xv.astype(xv.dtype.newbyteorder(">")).tobytes())
        np.testing.assert_allclose(acc[0], expected, rtol=1e-6)


def test_vectorised_float32_path_equals_the_scalar_loop_bit_for_bit():
    # float32 frames summed into one plane take the vectorised path; the same values as float64
    # take the scalar loop, which does the same arithmetic: the results must be identical,
    # whatever the span (starting and ending inside a 2048-pixel chunk) and the special values
    rng = np.random.default_rng(8)
    x = (10 ** rng.uniform(-1, 6, 10_000)).astype(np.float32)
    x[rng.integers(0, x.size, 40)] *= -1
    x[[5, 2047, 2048, 4100, 9999]] = [np.nan, np.inf, -np.inf, 5e4, -7e5]
    for name in ("typical", "pessimistic"):
        model = load_model(name)
        for dtype in (">f4", "<f4"):
            for span in [(0, x.size), (1, 2049), (2047, 6001), (3000, 3001)]:
                vec = np.full((1, x.size), 0.25)
                ref = np.full((1, x.size), 0.25)
                bad_v, sum_v = accumulate(x.astype(dtype), vec, [3.5], model, scale=1.7, span=span)
                bad_r, _ = accumulate(x.astype(np.float64), ref, [3.5], model, scale=1.7, span=span)
                assert bad_v == bad_r == int((~np.isfinite(x[span[0]:span[1]])).sum())
                np.testing.assert_array_equal(vec, ref)
                whole = x.astype(">f4")[span[0]:span[1]].tobytes()
                assert sum_v == _kernels.datasum(whole)


def test_kernel_max_combine_and_several_planes_and_threads():
    rng = np.random.default_rng(4)
    model = load_model("pessimistic")
    a, b = 10 ** rng.uniform(0, 6, (2, 300, 1000))
    acc = np.zeros((2, 300, 1000))
    n = a.size
    halves = [(0, n // 2), (n // 2, n)]

    def both(x, factors, **kw):
        with ThreadPoolExecutor(2) as pool:
            return [f.result() for f in [pool.submit(accumulate, x, acc, factors, model, span=s, **kw)
                                         for s in halves]]

    both(a, [1.0, 3.0], combine="max")
    both(b, [2.0, 1.0], combine="max")
    np.testing.assert_allclose(acc[0], np.maximum(model.F(a), 2 * model.F(b)), rtol=1e-14)
    np.testing.assert_allclose(acc[1], np.maximum(3 * model.F(a), model.F(b)), rtol=1e-14)
    summed = np.zeros((1, 300, 1000))
    parts = []
    for span in [(0, n // 3), (n // 3, 2 * n // 3), (2 * n // 3, n)]:
        parts.append(accumulate(a, summed, [1.0], model, scale=2.0, span=span)[1])
    np.testing.assert_allclose(summed[0], model.F(2 * a), rtol=1e-14)
    # DATASUMs of pieces combine by ones'-complement addition
    total = 0
    for part in parts:
        total = ones_complement_add(total, part)
    assert total == _kernels.datasum(a.astype(">f8").tobytes())


@pytest.mark.parametrize("gamma", [0.0, 0.3, 0.7, 0.999999, 1.0, 1.000001, 1.3, 2.0])
@pytest.mark.parametrize("window", [(0.5, 7.6), (30.0, 169.8), (1234.5, 1374.3), (5e5, 5e5 + 88.4)])
def test_time_factor_is_the_exact_integral(gamma, window):
    t1, t2 = window
    expected, err = integrate.quad(lambda t: (t / 1000.0) ** (-gamma), t1, t2, epsabs=0, epsrel=1e-13)
    assert float(time_factor(t1, t2, gamma)) == pytest.approx(expected, rel=1e-10)


def test_time_factor_edge_cases():
    assert float(time_factor(10.0, 10.0, 1.0)) == 0.0
    assert float(time_factor(0.0, 100.0, 0.5)) == pytest.approx(2 * 1000 ** 0.5 * 10.0, rel=1e-12)
    with pytest.raises(ValueError):
        time_factor(0.0, 100.0, 1.5)
    with pytest.raises(ValueError):
        time_factor(20.0, 10.0, 1.0)


def test_overrides_and_their_errors():
    model = load_model("typical", ["gamma=1.2", "A=0.02"])
    assert (model.gamma, model.A, model.x0) == (1.2, 0.02, 6.0e4)
    assert "gamma=1.2" in model.name
    with pytest.raises(PerscliError, match="unknown persistence parameter 'beta'"):
        load_model("typical", ["beta=1"])
    with pytest.raises(PerscliError, match="gamma must be a finite number"):
        load_model("typical", ["gamma=fast"])
    with pytest.raises(PerscliError, match="KEY=VALUE"):
        load_model("typical", ["gamma"])
    with pytest.raises(PerscliError, match="must be positive"):
        load_model("typical", ["dx=0"])
    with pytest.raises(PerscliError, match="unknown persistence model"):
        load_model("optimistic")
    with pytest.raises(PerscliError, match="linear"):
        load_model("galsim-linear", ["gamma=2"])


def test_yaml_models(tmp_path):
    full = tmp_path / "full.yaml"
    full.write_text("A: 0.03\nx0: 7.0e4\ndx: 3.0e4\nalpha: 0.05\ngamma: 1.1\nhalf_well: 4.0e4\n")
    model = load_model(str(full))
    assert (model.A, model.x0, model.dx, model.alpha, model.gamma, model.half_well) == (
        0.03, 7.0e4, 3.0e4, 0.05, 1.1, 4.0e4)
    section = tmp_path / "detector.yaml"
    section.write_text("persistence:\n  base: pessimistic\n  gamma: 0.9\n")
    model = load_model(str(section))
    assert (model.A, model.gamma) == (0.086, 0.9)
    linear = tmp_path / "linear.yaml"
    linear.write_text("kind: linear\ncoefficients: [1.0e-3, 5.0e-4]\n")
    assert load_model(str(linear)).coefficients == (1e-3, 5e-4)
    typo = tmp_path / "typo.yaml"
    typo.write_text("A: 0.03\nx_0: 7.0e4\n")
    with pytest.raises(PerscliError, match="unknown persistence parameter.*x_0"):
        load_model(str(typo))
    partial = tmp_path / "partial.yaml"
    partial.write_text("A: 0.03\n")
    with pytest.raises(PerscliError, match="missing x0"):
        load_model(str(partial))
    bad = tmp_path / "bad.yaml"
    bad.write_text("A: [unclosed\n")
    with pytest.raises(PerscliError, match="not valid YAML"):
        load_model(str(bad))
    with pytest.raises(PerscliError, match="not found"):
        load_model(str(tmp_path / "absent.yaml"))


def test_galsim_linear_coefficients_are_galsims():
    galsim_roman = pytest.importorskip("galsim.roman")
    np.testing.assert_allclose(GALSIM_LINEAR_COEFFICIENTS, galsim_roman.persistence_coefficients, rtol=1e-12)
    np.testing.assert_allclose(
        [getattr(PersistenceModel(), k) for k in ("A", "x0", "dx", "alpha", "gamma", "half_well")],
        galsim_roman.persistence_fermi_parameters, rtol=1e-15)


# -- the wfc3 preset and the WFC3 pipeline's conventions --------------------------------------------------

def test_wfc3_preset_is_stsci_s_fermi_law_with_the_pipeline_s_conventions():
    model = load_model("wfc3")
    # NOTES.md section 1: norm 0.3, alpha 0.174, gamma 1.0, x0 9.0e4, dx 2.0e4; no linear branch
    assert (model.A, model.x0, model.dx, model.alpha, model.gamma, model.half_well) == (
        0.3, 9.0e4, 2.0e4, 0.174, 1.0, 0.0)
    assert (model.time_model, model.combine, model.max_previous, model.lookback) == ("middle", "max", 0, 16.0)
    x = np.array([-5.0, 0.0, 1.0, 1.0e3, 4.0e4, 9.0e4, 2.0e5, 1.0e7])
    long = np.where(x > 0, 0.3 / (np.exp(-(x - 9.0e4) / 2.0e4) + 1.0) * (np.clip(x, 0, None) / 9.0e4) ** 0.174, 0)
    np.testing.assert_allclose(model.F(x), long, rtol=1e-14, atol=0)
    assert model.F([9.0e4])[0] == pytest.approx(0.15)  # half the normalisation at the Fermi step
    # the compiled kernel has no linear branch either (half_well = 0), on every path
    for dtype in ("<f8", ">f4"):
        for combine, planes in (("sum", [2.0]), ("max", [2.0]), ("sum", [1.0, 2.0])):
            acc = np.zeros((len(planes), x.size))
            accumulate(x.astype(dtype), acc, planes, model, combine=combine)
            np.testing.assert_allclose(acc, np.outer(planes, model.F(x.astype(dtype).astype(float))),
                                       rtol=1e-12, atol=0)
    # the other presets keep the paper's conventions
    assert (load_model("typical").time_model, load_model("typical").lookback) == ("exact", 0.0)


def test_wfc3_settings_can_be_overridden_and_come_with_base_wfc3(tmp_path):
    model = load_model("wfc3", ["lookback=0", "combine=sum", "time_model=exact"])
    assert (model.lookback, model.combine, model.time_model, model.A) == (0.0, "sum", "exact", 0.3)
    path = tmp_path / "mine.yaml"
    path.write_text("base: wfc3\nA: 0.25\nlookback: 24\n")
    model = load_model(str(path))
    assert (model.A, model.x0, model.lookback, model.combine, model.time_model) == (0.25, 9.0e4, 24.0, "max",
                                                                                     "middle")
    for bad in ("lookback=-1", "lookback=nan", "lookback=soon", "half_well=-1"):
        with pytest.raises(PerscliError, match=bad.split("=")[0]):
            load_model("wfc3", [bad])


def test_middle_time_factor_is_the_rate_at_mid_window_times_the_window():
    from perscli.detector.persistence import exposure_time_factors, middle_time_factor

    gap, windows = 600.0, np.array([0.0, 7.0, 50.0, 300.0])
    np.testing.assert_allclose(middle_time_factor(gap, windows, 1.0),
                               [0.0, 7.0 * 1000 / 603.5, 50.0 * 1000 / 625.0, 300.0 * 1000 / 750.0], rtol=1e-14)
    np.testing.assert_allclose(middle_time_factor(gap, windows[1:], 1.3),
                               windows[1:] * ((gap + windows[1:] / 2) / 1000.0) ** -1.3, rtol=1e-14)
    # the rate is convex in t: its value at mid-window underestimates the integral, by less for longer gaps
    for g in (30.0, 600.0, 36000.0):
        exact = float(time_factor(g, g + 300.0, 1.0))
        mid = float(middle_time_factor(g, 300.0, 1.0)[0])
        assert mid < exact and (exact - mid) / exact < {30.0: 0.35, 600.0: 0.02, 36000.0: 1e-5}[g]
    model = load_model("wfc3")
    assert exposure_time_factors(gap, windows, 0, model) == list(middle_time_factor(gap, windows, 1.0))
    # no divergence at zero delay for the middle convention, unlike the exact integral
    assert exposure_time_factors(0.0, [100.0], 0, model) == [100.0 * 1000 / 50.0]


def test_lookback_orders_and_drops_old_exposures():
    from perscli.detector.persistence import beyond_lookback, order_earlier

    model = load_model("wfc3")
    # ends in MJD: 20 h, 15 h and 1 h before the start
    start = 60000.0
    ends = [start - 20 / 24, start - 15 / 24, start - 1 / 24]
    assert beyond_lookback(ends, start, model, unit_seconds=86400.0) == [0]
    keep, left = order_earlier(ends, start, model, unit_seconds=86400.0)
    assert (keep, left) == ([2, 1], [0])
    # the same in seconds
    keep, _ = order_earlier([(e - start) * 86400 for e in ends], 0.0, model)
    assert keep == [2, 1]
    # no limit, and max_previous still applies after the look-back
    assert order_earlier(ends, start, load_model("wfc3", ["lookback=0"]), unit_seconds=86400.0)[0] == [2, 1, 0]
    capped = load_model("wfc3", ["max_previous=1"])
    assert order_earlier(ends, start, capped, unit_seconds=86400.0) == ([2], [0, 1])


def test_one_table_of_persistence_parameters_makes_the_schema_presets_law_and_options():
    """A persistence parameter is written once (settings.PERSISTENCE_PARAMETERS); everything else is made from it."""
    import dataclasses

    from perscli.cli.apply_persistence import apply_persistence
    from perscli.detector.effects import Persistence
    from perscli.detector.settings import (DEFAULT_PRESET, FERMI_PARAMETERS, PERSISTENCE_PARAMETERS,
                                           PRESET_NAMES, SETTINGS)

    table = {p.name: p for p in PERSISTENCE_PARAMETERS}
    assert [p.name for p in Persistence.schema] == list(table)
    for p in PERSISTENCE_PARAMETERS:
        if p.group:
            # a value that comes with the preset: one for every preset, none of its own
            assert set(p.presets) == set(PRESET_NAMES), p.name
            assert p.default is None
    assert FERMI_PARAMETERS == ("A", "x0", "dx", "alpha", "gamma", "half_well")
    assert SETTINGS == ("time_model", "combine", "max_previous", "lookback")
    # every preset, loaded by name, is the table's column
    for preset in PRESET_NAMES:
        model = load_model(preset)
        for key in (*FERMI_PARAMETERS, *SETTINGS):
            assert getattr(model, key) == table[key].presets[preset], (preset, key)
    # the law's fields: each one a parameter of the table, its default the table's (for the default preset)
    for f in dataclasses.fields(PersistenceModel):
        if f.name == "name":
            continue
        p = table[f.name]
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        expected = p.presets[DEFAULT_PRESET] if p.presets else p.default
        assert (list(default) if f.name == "coefficients" else default) == expected, f.name
    # apply-persistence's options of the settings take their type and range from the table
    options = {o.name: o for o in apply_persistence.params}
    for key in SETTINGS:
        p, option = table[key], options[key]
        if p.kind == "choice":
            assert tuple(option.type.choices) == p.choices
        else:
            assert option.type.min == p.lo
        assert option.default is None      # None: the law's own (per preset), said in the help
        for preset in PRESET_NAMES:
            value = p.presets[preset]
            assert (f"{value:g}" if isinstance(value, float) else str(value)) in option.help
