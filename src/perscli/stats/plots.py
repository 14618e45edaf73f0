"""Figures of ``perscli correlate``: xi+/- of De, the histogram of |De|, De's position angle."""

from __future__ import annotations

import numpy as np

from .de_stats import MIN_EXPECTED


def _pyplot():
    import matplotlib  # lazy: figures only for --plot; matplotlib.use is process-wide

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the backend is chosen

    return plt


def xi_figure(xi: dict, png: str, *, sep_units: str = "arcmin", title: str = "",
              errors: str = "jackknife errors") -> None:
    """xi+ and xi- of De against separation, with their errors, one panel each.

    The y axes are symmetric-log, linear within the median error of zero,
    so that a signal over orders of magnitude and a noise-dominated
    measurement (values of either sign) both read clearly.  The legend sits
    below the axes, so that it hides no point.

    Parameters
    ----------
    xi : dict
        TreeCorr's columns (meanr, xip, xim, sigma_xip, sigma_xim, npairs).
    png : str
        Output path.
    sep_units : str
        Units of meanr, for the axis label.
    title : str
        Figure title.
    errors : str
        What the error bars are, for the legend ('jackknife errors', 'shot-noise errors').
    """
    plt = _pyplot()
    fig, axes = plt.subplots(2, 1, figsize=(6.4, 6.8), sharex=True)
    ok = np.asarray(xi["npairs"]) > 0
    r = np.asarray(xi["meanr"])[ok]
    for ax, key, colour, label in ((axes[0], "xip", "C0", r"$\xi_+$"), (axes[1], "xim", "C3", r"$\xi_-$")):
        val = np.asarray(xi[key])[ok]
        err = np.asarray(xi[f"sigma_{key}"])[ok]
        ax.errorbar(r, val, yerr=err, fmt="o", color=colour, ms=4, capsize=2,
                    label=f"{label} of $\\Delta e$ ({errors})")
        ax.axhline(0.0, color="k", lw=0.6)
        scale = np.median(err[err > 0]) if np.any(err > 0) else 0.0
        if scale > 0 and np.max(np.abs(val) + err, initial=0) > 10 * scale:
            ax.set_yscale("symlog", linthresh=scale)
        ax.set_ylabel(label)
    # one legend below the axes, never over them: in the upper right corner of each panel it hid the
    # points at the largest separations (4-6 arcmin and beyond), which are often the highest ones
    handles = [h for ax in axes for h in ax.get_legend_handles_labels()[0]]
    labels = [lab for ax in axes for lab in ax.get_legend_handles_labels()[1]]
    axes[1].legend(handles, labels, frameon=False, fontsize=8, ncol=2, loc="upper center",
                   bbox_to_anchor=(0.5, -0.22))
    if not ok.any():
        # no pair at all (a handful of objects): an empty figure that says so, on the nominal range
        rnom = np.asarray(xi["r_nom"], dtype=float)
        axes[1].set_xlim(rnom.min() / 1.2, rnom.max() * 1.2)
        for ax in axes:
            # above the zero line (mid-height), not through it
            ax.text(0.5, 0.7, "no pair in any separation bin", transform=ax.transAxes, ha="center")
    axes[1].set_xscale("log")
    axes[1].set_xlabel(rf"$\theta$ ({sep_units})")
    axes[0].set_title(title if len(title) < 70 else title[:67] + "...", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=100, format="png")
    plt.close(fig)


def hist_de_figure(hist: dict, png: str, *, thresholds=(), n: int | None = None) -> None:
    """Histogram of |De| on log bins (the paper's hist_de), with the thresholds marked.

    Parameters
    ----------
    hist : dict
        de_lo, de_hi, count (first row: underflow [0, lo); last: overflow [hi, inf)).
    png : str
        Output path.
    thresholds : sequence of float
        |De| thresholds to mark.
    n : int, optional
        Number of objects, for the title.
    """
    plt = _pyplot()
    lo, hi, count = (np.asarray(hist[k]) for k in ("de_lo", "de_hi", "count"))
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    inner = slice(1, len(count) - 1)
    edges = np.append(lo[inner], hi[inner][-1])
    ax.stairs(count[inner], edges, color="C0", fill=True, alpha=0.6)
    ax.set_xscale("log")
    if count[inner].max(initial=0) > 0:
        ax.set_yscale("log")
    for t in thresholds:
        ax.axvline(t, color="C3", ls="--", lw=1)
        ax.text(t, 1.0, f" {t:g}", color="C3", transform=ax.get_xaxis_transform(), va="top", fontsize=8)
    ax.set_xlabel(r"$|\Delta e|$")
    ax.set_ylabel("objects per bin")
    notes = [f"|De| < {hi[0]:g}: {int(count[0])}"]
    if count[-1]:
        notes.append(f"|De| >= {lo[-1]:g}: {int(count[-1])}")
    ax.text(0.02, 0.97, "\n".join(notes), transform=ax.transAxes, va="top", fontsize=8)
    ax.set_title(f"{n} objects" if n is not None else "")
    fig.tight_layout()
    fig.savefig(png, dpi=100, format="png")
    plt.close(fig)


def theta_figure(theta: dict, png: str) -> None:
    """|De|-weighted distribution of De's position angle per |De| bin (the paper's bin_theta).

    Bootstrap error bars; the legend, below the axes, gives each |De| bin's
    chi2 against uniform (with the variance under uniform), its degrees of
    freedom and p-value.

    The y axis is scaled to the bins with enough objects for their
    fractions to mean something: an expected (weighted) count n_eff /
    nangle of at least :data:`perscli.stats.de_stats.MIN_EXPECTED` per
    angle bin, the rule that also chooses the chi2 p-value.  A bin with
    fewer (three galaxies put fractions of 1/3 and error bars of 0.5 into a
    plot of fractions near 1/18) is drawn faint, and its points beyond the
    axis as triangles at the edge, instead of setting the scale and
    flattening every other bin.  When no bin has enough objects, all of them
    set it.
    """
    plt = _pyplot()
    lo, hi, n = (np.asarray(theta[k]) for k in ("de_lo", "de_hi", "n"))
    t0, t1 = np.asarray(theta["theta_lo"]), np.asarray(theta["theta_hi"])
    frac, err, chi2 = (np.asarray(theta[k]) for k in ("frac", "frac_err", "chi2_uniform"))
    pvalue = np.asarray(theta.get("p_uniform", np.full(len(frac), np.nan)))
    neff = np.asarray(theta.get("n_eff", n), dtype=float)
    bins = sorted(set(zip(lo.tolist(), hi.tolist())))
    nangle = int(np.sum((lo == bins[0][0]) & (hi == bins[0][1]))) if bins else 1
    drawn = [(k, (a, b)) for k, (a, b) in enumerate(bins) if n[(lo == a) & (hi == b)][0] > 0]
    sparse = {k: bool(neff[(lo == a) & (hi == b)][0] / nangle < MIN_EXPECTED) for k, (a, b) in drawn}
    scaling = [kb for kb in drawn if not sparse[kb[0]]] or drawn
    fig, ax = plt.subplots(figsize=(6.4, 4.6 + 0.2 * (len(drawn) + 1)))
    # y range: the scaling bins' points with their error bars, and the uniform level
    ylo, yhi = 1.0 / nangle, 1.0 / nangle
    for _, (a, b) in scaling:
        sel = (lo == a) & (hi == b)
        e = np.nan_to_num(err[sel], nan=0.0)
        ylo = min(ylo, float(np.nanmin(frac[sel] - e)))
        yhi = max(yhi, float(np.nanmax(frac[sel] + e)))
    ylo = max(ylo, 0.0)
    pad = 0.08 * (yhi - ylo) if yhi > ylo else 0.5 / nangle
    ylim = (ylo - pad, yhi + pad)
    for k, (a, b) in drawn:
        sel = (lo == a) & (hi == b)
        centre = 0.5 * (t0[sel] + t1[sel]) + (k - len(bins) / 2) * 0.8
        label = (rf"{a:g} $\leq |\Delta e| <$ {b:g} (N={int(n[sel][0])}, "
                 rf"$\chi^2$={chi2[sel][0]:.1f}/{nangle - 1}, p={pvalue[sel][0]:.2g})")
        faint = sparse[k] and len(scaling) < len(drawn)
        if not faint:
            ax.errorbar(centre, frac[sel], yerr=err[sel], fmt="o-", ms=3, lw=0.8, capsize=2, label=label)
            continue
        # points and error bars only, no line: a line through noise would draw a shape that is not there
        line = ax.errorbar(centre, frac[sel], yerr=err[sel], fmt="o", ms=3, lw=0.6, capsize=2, alpha=0.4,
                           mfc="none", label=label + ": few objects, not to scale")
        colour = line[0].get_color()
        above, below = frac[sel] > ylim[1], frac[sel] < ylim[0]
        ax.plot(centre[above], np.full(above.sum(), ylim[1]), "^", color=colour, alpha=0.6, ms=5, clip_on=False)
        ax.plot(centre[below], np.full(below.sum(), ylim[0]), "v", color=colour, alpha=0.6, ms=5, clip_on=False)
    ax.axhline(1.0 / nangle, color="k", ls="--", lw=1, label="uniform")
    ax.set_ylim(*ylim)
    ax.set_xlim(-90, 90)
    ax.set_xticks(np.arange(-90, 91, 30))
    ax.set_xlabel(r"position angle of $\Delta e$ (deg)")
    ax.set_ylabel(r"$|\Delta e|$-weighted fraction")
    # below the axes: inside, the labels of several bins covered the points
    ax.legend(frameon=False, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14))
    if not drawn:
        # above the uniform level's line (mid-height), not through it
        ax.text(0.5, 0.7, "no object in the |De| bins", transform=ax.transAxes, ha="center")
    fig.tight_layout()
    fig.savefig(png, dpi=100, format="png")
    plt.close(fig)
