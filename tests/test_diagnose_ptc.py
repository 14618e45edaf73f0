"""diagnose's photon-transfer gain of self-predicted ramps: measured where the ramps hold a photon-transfer case,
and where they do not, a statement of why instead of a number.

The ramps with a known gain are made here by numpy (not by perscli): WFC3-IR-like MULTIACCUM files of 266 x 266
pixels (a 5-pixel border of reference pixels that see no light and are quieter), a bias, sky and stars of
constant rates, Poisson noise in electrons, read noise, a gain unlike the header's, rounding to DN.  Variants
break the photon-transfer case the way real data do: light that arrives in bursts (a spatial scan) and two
exposures whose scenes differ by a few per cent.
"""

import numpy as np
import pytest

from fits_factory import wfc3_ramp_file

MJD = 56000.0
#: SAMPTIMEs of a WFC3-IR SPARS10 ramp of 9 reads (s)
TIMES = np.array([0.0, 0.1128, 7.294, 14.475, 21.657, 28.838, 36.020, 43.201, 50.382])
HEADER_GAIN = 2.5


def scene(rng, n=266, stars=90):
    """Rates in e-/s: a sky of 1.5 e-/s and Gaussian stars whose peaks span 10 to 700 e-/s."""
    yy, xx = np.mgrid[0:n, 0:n]
    rates = np.full((n, n), 1.5)
    for _ in range(stars):
        y, x = rng.uniform(8, n - 8, 2)
        peak = 10.0 ** rng.uniform(1.0, np.log10(700.0))
        rates += peak * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * rng.uniform(1.2, 3.0) ** 2))
    return rates


def ramp(path, rng, rates, *, gain, start=MJD, read_e=15.0, ref_read_e=9.0, burst=False):
    """A WFC3-IR raw ramp of ``rates`` (e-/s) read out at :data:`TIMES` with ``gain`` e-/DN (the header says
    :data:`HEADER_GAIN`).  ``burst``: each pixel's light arrives within one interval, at a time that moves
    along the rows, as a spatial scan brings it (the same electrons over the exposure)."""
    n = rates.shape[0]
    light = np.zeros((n, n), dtype=bool)
    light[5:-5, 5:-5] = True                      # the reference border sees no light
    noise = np.where(light, read_e, ref_read_e)
    bias = rng.normal(12000.0, 30.0, (n, n))
    charge = np.zeros((n, n))
    reads = []
    total = TIMES[-1]
    scan_at = 1 + (np.arange(n)[:, None] * (len(TIMES) - 2) // n) * np.ones((1, n), dtype=int)
    for k, t in enumerate(TIMES):
        if k:
            dt = t - TIMES[k - 1]
            mean = rates * (total * (scan_at == k) if burst else dt)
            charge += np.where(light, rng.poisson(mean), 0.0)
        reads.append(np.round(bias + (charge + rng.normal(0.0, noise)) / gain).astype(np.float32))
    prim = {"INSTRUME": "WFC3", "DETECTOR": "IR", "EXPSTART": start, "EXPEND": start + total / 86400.0,
            "EXPTIME": total, "CCDGAIN": HEADER_GAIN, "NSAMP": len(TIMES)}
    return wfc3_ramp_file(path, reads, TIMES, {"BUNIT": "COUNTS"}, primary_keywords=prim)


def transfer(*paths):
    from perscli.diagnose.data import read_measured
    from perscli.diagnose.ramp import photon_transfer

    exposures = read_measured([str(p) for p in paths])
    return photon_transfer(exposures, exposures[0].gain)


@pytest.mark.parametrize("true_gain", [2.2, 2.5])
def test_a_constant_light_ramp_and_a_pair_measure_the_gain_to_5_percent(tmp_path, true_gain):
    """One ramp (its second differences) and a pair of ramps of one scene (their difference): the gain within
    5% of the one the ramps were made with, trusted, and said to refute or support the header's."""
    rng = np.random.default_rng(7)
    rates = scene(rng)
    a = ramp(tmp_path / "a_raw.fits", rng, rates, gain=true_gain)
    b = ramp(tmp_path / "b_raw.fits", rng, rates, gain=true_gain, start=MJD + 0.01)
    for pt in (transfer(a), transfer(a, b)):
        assert pt["trusted"], pt["verdict"]
        assert abs(pt["gain"] / true_gain - 1.0) < 0.05, (pt["gain"], pt["gain_error"], pt["method"])
        assert pt["gain_error"] < 0.05 * pt["gain"]
        agrees = abs(true_gain - HEADER_GAIN) < 0.05 * HEADER_GAIN
        assert ("supports" if agrees else "refutes") in pt["verdict"], pt["verdict"]


def test_light_that_changes_during_the_ramp_gives_a_reason_not_a_gain(tmp_path):
    """A spatial scan: every pixel's light arrives within one interval.  The second differences hold the
    change of the light; only the sky's pixels are constant, and the report says so instead of a gain."""
    rng = np.random.default_rng(8)
    pt = transfer(ramp(tmp_path / "scan_raw.fits", rng, scene(rng), gain=2.2, burst=True))
    assert not pt["trusted"] and pt["gain"] is None
    assert "changes during the ramp" in pt["verdict"] and "header gain (2.5) is kept" in pt["verdict"]
    assert pt["changing_share"] > 0.5


def test_two_ramps_whose_scenes_differ_give_a_reason_not_a_gain(tmp_path):
    """The second exposure's stars are 3% brighter or fainter, each its own way (a variable field, a pointing
    that moved): their difference is not noise, and the report says so."""
    rng = np.random.default_rng(9)
    rates = scene(rng)
    other = np.where(rates > 5.0, rates * rng.normal(1.0, 0.03, rates.shape), rates)
    a = ramp(tmp_path / "a_raw.fits", rng, rates, gain=2.2)
    b = ramp(tmp_path / "b_raw.fits", rng, other, gain=2.2, start=MJD + 0.01)
    pt = transfer(a, b)
    assert not pt["trusted"] and pt["gain"] is None
    assert "scenes differ" in pt["verdict"], pt["verdict"]
