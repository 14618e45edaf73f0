"""The paper's Figs. 1 and 2, made with perscli's own drawing and persistence law.

Fig. 1: the persistence that stars of several J magnitudes leave in the next
exposure (Roman's 30 s gap, a 139.8 s exposure, the 'typical' law), beside
J=22 and J=24 galaxies in one exposure; Fig. 2: a J=22 galaxy 51 pixels
from the ghost of a J=7 star.  256x256 stamps at Roman's pixel scale.
"""

from __future__ import annotations

import io

import galsim
import numpy as np

from ..detector.model import load_persistence_model
from ..detector.persistence import persistence_charge
from ..instrument import ROMAN_EXPTIME, ROMAN_FULL_WELL, ROMAN_WAS_GAP
from ..optics import Optics, StampDrawer, to_pixels
from ..render.exposure import Exposure

STAR_MAGS = (7, 11, 15, 17, 19, 21)
GALAXY_MAGS = (22, 24)
STAMP = 256


def _optics():
    # SCA 1 at the field of the bundled examples; the PSF and zeropoint are what matter here
    return Optics(Exposure(ra=10.0, dec=-44.0, pa=30.0, sca=1, filter="J129", mjd=61541.97))


def _drawer(optics):
    return StampDrawer(optics.psf_pixels)


def star_fluence(optics, drawer, mag: float, n: int = STAMP) -> np.ndarray:
    """Electrons a star of J=mag deposits over one exposure, on an n x n stamp (saturation not applied)."""
    return drawer.stamp(n, 0.0, 0.0, float(optics.electrons(mag)))


def ghost(fluence: np.ndarray, *, model: str = "typical", gap: float = ROMAN_WAS_GAP, exptime: float = ROMAN_EXPTIME,
          full_well: float = ROMAN_FULL_WELL) -> np.ndarray:
    """Persistence charge (e-) in the next exposure from one earlier exposure's fluence.

    The fluence is capped at the full well, as a saturated pixel's is in the
    study's frames.
    """
    x = np.minimum(fluence, full_well)
    return persistence_charge([x], [0.0], gap, [exptime], load_persistence_model(model))[0]


def galaxy(optics, drawer, mag: float, hlr: float = 0.3, g1: float = 0.2, n: int = STAMP) -> np.ndarray:
    prof = galsim.Exponential(half_light_radius=hlr, flux=1.0).shear(g1=g1, g2=0.0)
    prof = to_pixels(prof)
    return drawer.stamp(n, 0.0, 0.0, float(optics.electrons(mag)), prof)


def _pyplot():
    import matplotlib  # lazy: figures only in a study's summary; matplotlib.use is process-wide

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the backend is chosen

    return plt


def _png(fig) -> bytes:
    buf = io.BytesIO()
    # no software version or date in the file: the same figure, the same bytes
    fig.savefig(buf, dpi=100, format="png", metadata={"Software": None})
    return buf.getvalue()


def ghost_stamps() -> bytes:
    """Fig. 1 as PNG bytes."""
    plt = _pyplot()
    from matplotlib.colors import LogNorm  # lazy: matplotlib (_pyplot)

    optics = _optics()
    drawer = _drawer(optics)
    panels = [(f"ghost of a J={m} star", ghost(star_fluence(optics, drawer, m))) for m in STAR_MAGS]
    panels += [(f"J={m} galaxy", galaxy(optics, drawer, m)) for m in GALAXY_MAGS]
    fig, axes = plt.subplots(2, 4, figsize=(13, 6.6))
    for ax, (title, img) in zip(axes.ravel(), panels):
        peak = float(img.max())
        im = ax.imshow(np.maximum(img, peak * 1e-4), origin="lower", cmap="magma",
                       norm=LogNorm(vmin=peak * 1e-4, vmax=peak))
        ax.set_title(f"{title}\npeak {peak:.3g} e-", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02).set_label("e-", fontsize=8)
    fig.suptitle("Persistence of stars in the next 139.8 s exposure (30 s gap, typical law, full well 1e5 e-) "
                 "and galaxies in one exposure, Roman J129, 256x256 pixels", fontsize=10)
    fig.tight_layout()
    data = _png(fig)
    plt.close(fig)
    return data


def galaxy_beside_ghost() -> bytes:
    """Fig. 2 as PNG bytes: a J=22 galaxy 51 pixels from the ghost of a J=7 star."""
    plt = _pyplot()

    optics = _optics()
    drawer = _drawer(optics)
    g = ghost(star_fluence(optics, drawer, 7.0))
    gal = galaxy(optics, drawer, 22.0)
    # the galaxy 51 pixels to the right of the star's centre
    img = g + np.roll(gal, 51, axis=1)
    fig, ax = plt.subplots(figsize=(6.4, 5.4))
    im = ax.imshow(img, origin="lower", cmap="magma", vmin=0, vmax=float(np.percentile(img, 99.95)))
    ax.set_title("J=22 galaxy 51 pixels from the ghost of a J=7 star", fontsize=10)
    ax.set_xlabel("x (pixels)")
    ax.set_ylabel("y (pixels)")
    fig.colorbar(im, ax=ax).set_label("electrons")
    fig.tight_layout()
    data = _png(fig)
    plt.close(fig)
    return data


def xi_against_budget(combined: list, nreal: int) -> bytes:
    """|xi+| of De per separation for every variant, with its error, against the additive budget (PNG bytes).

    Parameters
    ----------
    combined : list of dict
        :func:`perscli.study.summary.combine_realisations` of each variant
        (its ``xi`` bins: theta, xip, error, budget, verdict).
    nreal : int
        Realisations behind each point (for the legend).

    One panel: the budget as a line, each variant's |xi+| as points (filled
    where xi+ > 0, open where negative) with 2-sigma bars, on log axes:
    where a bar stays below the line the data tell xi+ is below the budget.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    budget = None
    for k, res in enumerate(combined):
        bins = res.get("xi") or []
        if not bins:
            continue
        theta = np.array([b["theta"] for b in bins], dtype=float) * (1.0 + 0.03 * (k - (len(combined) - 1) / 2))
        xip = np.array([b["xip"] for b in bins], dtype=float)
        err = np.array([b["error"] for b in bins], dtype=float)
        budget = (np.array([b["theta"] for b in bins], dtype=float), np.array([b["budget"] for b in bins], dtype=float))
        colour = f"C{k}"
        low = np.maximum(np.abs(xip) - 2 * err, np.abs(xip) * 1e-3)
        ax.errorbar(theta, np.abs(xip), yerr=[np.abs(xip) - low, 2 * err], fmt="none", ecolor=colour, alpha=0.6)
        pos = xip > 0
        ax.plot(theta[pos], xip[pos], "o", color=colour, label=f"{res['variant']} ($\\xi_+ > 0$)")
        ax.plot(theta[~pos], -xip[~pos], "o", mfc="none", color=colour, label=f"{res['variant']} ($\\xi_+ < 0$)")
    if budget is not None:
        ax.plot(*budget, "k-", lw=1.5, label="Roman additive budget")
    ax.set_xscale("log")
    ax.set_yscale("log")
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter  # lazy: matplotlib (_pyplot)

    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel(r"$\theta$ (arcmin)")
    ax.set_ylabel(r"$|\xi_+|$ of $\Delta e$")
    ax.set_title(f"$\\xi_+$ of $\\Delta e$ against the budget ({nreal} realisation{'s' if nreal != 1 else ''}; "
                 "2$\\sigma$ bars)", fontsize=10)
    ax.legend(frameon=False, fontsize=8, loc="lower left")
    return _png(fig)
