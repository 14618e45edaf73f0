"""A picture of a rendered frame: the image, and the persistence it carries."""

from __future__ import annotations

import numpy as np


def frame_figure(sci: np.ndarray, png: str, *, persist: np.ndarray | None = None, title: str = "",
                 unit: str = "DN") -> None:
    """Write a PNG of a frame (asinh stretch) and, if given, its persistence (log scale).

    Parameters
    ----------
    sci : ndarray
        The frame.
    png : str
        Output path.
    persist : ndarray, optional
        Persistence in electrons, same shape.
    title : str
        Figure title.
    unit : str
        Units of ``sci`` for the colour bar.
    """
    import matplotlib  # lazy: figures only for --plot; matplotlib.use is process-wide

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the backend is chosen

    panels = 2 if persist is not None else 1
    fig, axes = plt.subplots(1, panels, figsize=(6.2 * panels, 5.6), squeeze=False)
    sky = float(np.median(sci))
    noise = float(np.median(np.abs(sci - sky))) * 1.4826 or 1.0
    shown = axes[0, 0].imshow(np.arcsinh((sci - sky) / (3 * noise)), origin="lower", cmap="gray",
                              vmin=-1, vmax=8, interpolation="nearest")
    axes[0, 0].set_title("frame (asinh, sky subtracted)")
    fig.colorbar(shown, ax=axes[0, 0], label=f"asinh((x - sky) / 3 sigma), {unit}")
    if persist is not None:
        shown = axes[0, 1].imshow(np.log10(np.clip(persist, 1e-3, None)), origin="lower", cmap="magma",
                                  vmin=-3, vmax=max(0.0, float(np.log10(max(persist.max(), 1e-3)))),
                                  interpolation="nearest")
        axes[0, 1].set_title("persistence from earlier exposures")
        fig.colorbar(shown, ax=axes[0, 1], label="log10 electrons")
    for ax in axes[0]:
        ax.set_xlabel("x (pixel)")
        ax.set_ylabel("y (pixel)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    plt.close(fig)
