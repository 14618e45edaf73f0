"""Measured frames made by code that does not call perscli's effects: a numpy detector chain of its own.

diagnose is tested on frames perscli's own effect code did not make, so that its verdicts are
not a consistency check of that code with itself.  The chain here follows the physics (and
galsim.roman's constants) written out again: Poisson noise of the sources and sky (the
simulation's IDEAL), reciprocity failure x (1 + a log10(x / t)), dark current, the persistence
of the earlier measured exposures (the Fermi law with its linear branch, integrated exactly over
the exposure), the full well, classical nonlinearity, interpixel capacitance, read noise, an
offset, the gain and rounding to DN; and effects that perscli's models do not describe:
row and column read noise, 1/f noise along the readout, hot pixels, a flat-field error, a shift of the PSF, cosmic
rays, persistence that decays exponentially in time, and persistence from saturated pixels only.

Each measured frame copies the headers of its simulated frame (timing, WCS, GAIN 1, BUNIT DN),
so diagnose pairs them; only the pixels differ.
"""

from __future__ import annotations

import math

import numpy as np

#: galsim.roman's constants and the paper's typical persistence law, written out again
#: (the IPC kernel is galsim.roman.ipc_kernel, read in :func:`roman_ipc`)
ROMAN = dict(dark=0.015, read_noise=8.5, gain=1.0, beta=-6e-7, reciprocity=0.0065, full_well=1e5, ipc=None,
             persistence_A=0.017, x0=6.0e4, dx=5.0e4, alpha=0.045, gamma=1.0, half_well=5.0e4, offset=0.0,
             bf=0.0)


def roman_ipc() -> np.ndarray:
    import galsim.roman

    return np.asarray(galsim.roman.ipc_kernel.array, dtype=np.float64)


def _fermi(x, p):
    x = np.asarray(x, dtype=np.float64)
    out = np.zeros_like(x)
    hw = p["half_well"]

    def law(v):
        return p["persistence_A"] / (np.exp(-(v - p["x0"]) / p["dx"]) + 1.0) * (v / p["x0"]) ** p["alpha"]

    above = x > hw
    out[above] = law(x[above])
    low = (x > 0) & ~above
    out[low] = law(np.array(hw)) * x[low] / hw
    return out


def _time_integral(t0, t1, p, law):
    if law == "power":
        g = p["gamma"]
        if abs(g - 1.0) < 1e-12:
            return 1000.0 * math.log(t1 / t0)
        return 1000.0 ** g * (t1 ** (1 - g) - t0 ** (1 - g)) / (1 - g)
    # exponential decay with the law's value at 1000 s: exp(-(t - 1000)/tau)
    tau = float(law)
    return tau * (math.exp(-(t0 - 1000.0) / tau) - math.exp(-(t1 - 1000.0) / tau))


def _ipc(img, kernel):
    padded = np.pad(img, 1)
    out = np.zeros_like(img)
    ny, nx = img.shape
    for j in range(3):
        for i in range(3):
            out += kernel[j, i] * padded[j:j + ny, i:i + nx]
    return out


def _read_sim(path):
    from astropy.io import fits

    with fits.open(path) as hdul:
        ideal = np.asarray(hdul["IDEAL"].data, dtype=np.float64)
        header = hdul["SCI"].header.copy()
    return ideal, header


def make_measured(sims, outdir, *, seed: int, **hidden):
    """Measured frames of the simulated ``sims`` (perscli render outputs, in time order) with hidden effects.

    Parameters
    ----------
    sims : sequence of str
    outdir : pathlib.Path
    seed : int
    hidden
        Changes to :data:`ROMAN` (dark, read_noise, gain, beta, reciprocity, ipc_alpha (the four
        nearest neighbours' coupling), persistence_A, offset, bf) and effects outside perscli's
        models: row_noise, col_noise (e- rms per row / column of each read), hot_fraction and
        hot_dark (e-/s), flat_rms (a smooth flat-field error, relative), shift (pixels, of the
        sources' light), cosmic_rays (hits per frame), persistence_tau (s: exponential decay),
        persistence_saturated_only (only pixels at the full well persist), one_over_f (e- rms of 1/f
        noise along the readout order).

    Returns
    -------
    list of str
    """
    from astropy.io import fits
    from scipy import ndimage

    p = dict(ROMAN)
    p["ipc"] = roman_ipc()
    extra = {k: hidden.pop(k) for k in ("row_noise", "col_noise", "hot_fraction", "hot_dark", "flat_rms", "shift",
                                        "cosmic_rays", "persistence_tau", "ipc_alpha", "one_over_f",
                                        "persistence_saturated_only") if k in hidden}
    unknown = set(hidden) - set(p)
    if unknown:
        raise ValueError(f"unknown hidden effects {unknown}")
    p.update(hidden)
    if "ipc_alpha" in extra:
        k = p["ipc"].copy()
        k[1, 1] = 0.0
        nn = (k[0, 1] + k[1, 0] + k[1, 2] + k[2, 1]) / 4.0
        k *= extra["ipc_alpha"] / nn
        k[1, 1] = 1.0 - k.sum()
        p["ipc"] = k
    rng = np.random.default_rng(seed)
    out, history = [], []
    shape = None
    flat = hot = None
    for k, sim in enumerate(sims):
        ideal, header = _read_sim(sim)
        shape = ideal.shape
        if flat is None:
            flat = np.ones(shape)
            if extra.get("flat_rms"):
                f = ndimage.gaussian_filter(rng.normal(size=shape), 6.0)
                flat = 1.0 + extra["flat_rms"] * f / f.std()
            hot = np.zeros(shape, dtype=bool)
            if extra.get("hot_fraction"):
                hot = rng.random(shape) < extra["hot_fraction"]
        t = float(header["EXPTIME"])
        start, end = float(header["EXPSTART"]), float(header["EXPEND"])
        x = ideal
        if extra.get("shift"):
            x = ndimage.shift(x, (0.0, extra["shift"]), order=3, mode="nearest")
        q = rng.poisson(np.clip(x * flat, 0, None)).astype(np.float64)
        pos = q > 0
        q[pos] = q[pos] * (1.0 + p["reciprocity"] * np.log10(q[pos] / t))
        q += rng.poisson(p["dark"] * t, size=shape)
        if hot.any():
            q[hot] += rng.poisson(extra.get("hot_dark", 5.0) * t, size=int(hot.sum()))
        law = extra.get("persistence_tau", "power")
        for fluence, end_prev in history[::-1][:10]:
            t0 = (start - end_prev) * 86400.0
            if extra.get("persistence_saturated_only"):
                # only the pixels that reached the full well persist (traps filled only beyond it)
                fluence = np.where(fluence >= p["full_well"], fluence, 0.0)
            q += _fermi(fluence, p) * _time_integral(t0, t0 + t, p, law)
        if p["bf"]:
            # brighter-fatter: a pixel's charge pushed to its neighbours in proportion to its square
            sq = q * q
            lap = np.zeros_like(q)
            lap[1:] += sq[:-1] - sq[1:]
            lap[:-1] += sq[1:] - sq[:-1]
            lap[:, 1:] += sq[:, :-1] - sq[:, 1:]
            lap[:, :-1] += sq[:, 1:] - sq[:, :-1]
            q = q + 0.5 * p["bf"] * lap
        q = np.minimum(q, p["full_well"])
        history.append((q.copy(), end))
        q = q + p["beta"] * q * q
        q = _ipc(q, p["ipc"])
        q += rng.normal(0.0, p["read_noise"], size=shape)
        if extra.get("row_noise"):
            q += rng.normal(0.0, extra["row_noise"], size=(shape[0], 1))
        if extra.get("col_noise"):
            q += rng.normal(0.0, extra["col_noise"], size=(1, shape[1]))
        if extra.get("one_over_f"):
            # 1/f noise in the order the pixels are read (row by row): power falling as 1/frequency
            n = shape[0] * shape[1]
            spec = np.fft.rfft(rng.normal(size=n))
            f = np.fft.rfftfreq(n)
            f[0] = f[1]
            stream = np.fft.irfft(spec / np.sqrt(f), n)
            q += (extra["one_over_f"] * stream / stream.std()).reshape(shape)
        if extra.get("cosmic_rays"):
            n = int(extra["cosmic_rays"])
            q[rng.integers(0, shape[0], n), rng.integers(0, shape[1], n)] += rng.uniform(500, 5000, n)
        q += p["offset"]
        dn = np.round(q / p["gain"])
        hdr = header.copy()
        for key in ("CHECKSUM", "DATASUM"):
            hdr.remove(key, ignore_missing=True, remove_all=True)
        hdr["BUNIT"] = "DN"
        hdr["GAIN"] = 1.0
        path = outdir / f"meas{k}.fits"
        fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(dn.astype(np.float32), header=hdr, name="SCI")]).writeto(
            path, overwrite=True, checksum=True)
        out.append(str(path))
    return out
