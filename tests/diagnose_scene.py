"""A small Roman scene rendered by perscli for the diagnose tests: the simulations that measured frames
(from :mod:`independent_chain`, or rendered with other settings) are compared with.

A cutout of SCA 7 with stars from J = 14 (saturated cores) to 22 and galaxies, a few exposures
169.8 s apart dithered by a few pixels, so that ghosts of earlier stars fall beside the stars.
"""

from __future__ import annotations

import numpy as np

from fits_factory import invoke

RA, DEC, PA, SCA, FILTER = 10.0, -44.0, 30.0, 7, "J129"
MJD1 = 61541.97
GAP = 30.0


def make_truth(path, *, bounds, nstars: int, ngalaxies: int, seed: int = 3, bright: float = 14.0) -> str:
    """A truth catalogue of stars and galaxies inside ``bounds`` (x0, x1, y0, y1 of SCA 7)."""
    from astropy.table import Table

    from perscli.render.exposure import Exposure
    from perscli.optics import Optics

    optics = Optics(Exposure(ra=RA, dec=DEC, pa=PA, sca=SCA, filter=FILTER, mjd=MJD1))
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(nstars + ngalaxies):
        x, y = rng.uniform(bounds[0] + 5, bounds[1] - 5), rng.uniform(bounds[2] + 5, bounds[3] - 5)
        ra, dec = optics.wcs.xyToradec(x, y, units="deg")
        kind = "star" if i < nstars else "galaxy"
        mag = rng.uniform(bright, 22) if kind == "star" else rng.uniform(19, 24)
        rows.append((i + 1, float(ra), float(dec), kind, mag, mag + 0.3, rng.uniform(0.2, 0.6),
                     rng.normal(0, 0.2), rng.normal(0, 0.2)))
    t = Table(rows=rows, names=["id", "ra", "dec", "kind", "mag_J129", "mag_H158", "hlr", "e1", "e2"])
    t["id"] = t["id"].astype(np.int64)
    t.write(path, format="fits", overwrite=True)
    return str(path)


def render_sequence(truth, outdir, *, bounds, n: int = 3, seed: int = 100, exptimes=None, settings=()) -> list:
    """``n`` exposures of ``truth`` (each with the earlier ones as --previous), rendered with ``settings``."""
    outdir.mkdir(parents=True, exist_ok=True)
    out, mjd = [], MJD1
    for k in range(n):
        exptime = exptimes[k] if exptimes else 139.8
        path = outdir / f"e{k}.fits"
        # a dither of a few pixels between exposures: ghosts fall beside the stars that made them
        args = ["render", truth, "--bounds", *bounds, "--ra", RA + k * 1.5e-4, "--dec", DEC, "--pa", PA,
                "--mjd", repr(mjd), "--filter", FILTER, "--sca", SCA, "--seed", seed + k, "--exptime", exptime,
                "--persistence-source", "all", "-o", path]
        # the FLUENCE of earlier exposures persists (not the default, the stars' light): the history that
        # diagnose's forward model and independent_chain use
        for s in settings:
            args += ["--set", s]
        for p in out:
            args += ["--previous", p]
        result = invoke(*args)
        assert result.exit_code == 0, (result.stderr, result.exception)
        out.append(str(path))
        mjd += (exptime + GAP) / 86400.0
    return out
