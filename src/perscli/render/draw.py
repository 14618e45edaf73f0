"""Drawing point sources and galaxies through a fixed PSF, exactly sampled, fast.

Why not GalSim's ``Convolve(galaxy, psf).drawImage()`` per object: it
recomputes the PSF's Fourier transform (an interpolated image, the expensive
part) for every object, on an FFT grid sized by the PSF's wide wings.  Here the
PSF times the pixel response (the PSF alone, with ``pixel=False``, for one that
includes it: shape fits through an effective PSF) is tabulated once per stamp
size; each object then costs its own analytic Fourier transform (GalSim's,
exact), a phase ramp for its sub-pixel position, a fold of the frequencies
above Nyquist onto the sampled band (the Poisson summation that makes pixel
values exact for an undersampled PSF), and one small inverse FFT.

Conventions: the PSF and the objects are in pixel coordinates of the detector
(GalSim's Roman PSFs are oriented with the SCA); an object's profile is mapped
from the sky with the WCS Jacobian at its own position; the PSF is the same
everywhere on the detector (the one at the SCA centre).
"""

from __future__ import annotations

import math

import numpy as np


def _centred_freqs(n: int, m: int) -> np.ndarray:
    """Angular frequencies (rad/pixel) of an m*n-point grid spaced 2 pi / n, zero at index m*n/2.

    This is the order of GalSim's k-images.  With m even, summing the m blocks of n
    (the aliasing fold) gives the n-point grid in FFT order directly: the block of a
    frequency changes in the centred order, its place within the block does not.
    """
    return 2.0 * np.pi / n * (np.arange(m * n) - m * n // 2)


class StampDrawer:
    """Draws objects convolved with one PSF into an image.

    Parameters
    ----------
    psf : galsim.GSObject
        The PSF in pixel coordinates (unit = one pixel), normalised to 1.
    pixel : bool
        Multiply by the pixel response (the default: ``psf`` is an optical
        PSF).  False when ``psf`` already includes it (an effective PSF, e.g.
        interpolated from a PSF image that was integrated over pixels):
        applying the pixel twice would widen the PSF by a pixel's variance.
    """

    def __init__(self, psf, pixel: bool = True):
        self.psf = psf
        self.pixel = bool(pixel)
        # alias factor: the grid must reach the PSF's maxk; an even factor keeps blocks aligned
        alias = max(1, math.ceil(psf.maxk / np.pi))
        self.alias = alias + (alias % 2)
        self._tables = {}

    @property
    def nbytes(self) -> int:
        """Bytes held by the tables made so far."""
        return sum(t.nbytes + k.nbytes for t, k in self._tables.values())

    def table(self, n: int):
        """(T, k) for stamp size n: PSF x pixel transfer (PSF only without ``pixel``) on the extended grid,
        and the frequencies."""
        table = self._tables.get(n)
        if table is None:
            m = self.alias
            k = _centred_freqs(n, m)
            psf_k = self.psf.drawKImage(nx=m * n, ny=m * n, scale=2.0 * np.pi / n).array
            if self.pixel:
                pix = np.sinc(k / (2.0 * np.pi))
                table = self._tables[n] = (psf_k * pix[:, None] * pix[None, :], k)
            else:
                table = self._tables[n] = (psf_k, k)
        return table

    def stamp(self, n: int, dx: float, dy: float, flux: float, profile=None) -> np.ndarray:
        """An n x n stamp of an object centred at (n/2 + dx, n/2 + dy) (array indices).

        Parameters
        ----------
        n : int
            Stamp size (even).
        dx, dy : float
            Sub-pixel offset of the centre, pixels.
        flux : float
            Total flux (electrons).
        profile : galsim.GSObject, optional
            The object's intrinsic profile in pixel coordinates, flux 1
            (None: a point source).
        """
        transfer, k = self.table(n)
        m = self.alias
        if profile is not None:
            field = profile.drawKImage(nx=m * n, ny=m * n, scale=2.0 * np.pi / n).array
            field *= transfer
        else:
            field = transfer.copy()
        field *= np.exp(-1j * k * dy)[:, None]
        field *= np.exp(-1j * k * dx)[None, :]
        folded = field.reshape(m, n, m, n).sum(axis=(0, 2))
        return np.fft.fftshift(np.fft.ifft2(folded).real) * flux

    def add(self, image: np.ndarray, x: float, y: float, flux: float, n: int, profile=None,
            origin=(1, 1)) -> bool:
        """Add an object at image position (x, y) (GalSim convention, pixel centres at integers).

        Parameters
        ----------
        image : ndarray
            Target array; ``image[0, 0]`` is pixel ``origin`` = (xmin, ymin).
        x, y : float
            Position of the centre.
        flux, n, profile
            See :meth:`stamp`.

        Returns
        -------
        bool
            Whether the stamp overlapped the image.
        """
        xmin, ymin = origin
        ix, iy = int(math.floor(x + 0.5)), int(math.floor(y + 0.5))
        # stamp array index [n/2, n/2] is pixel (ix, iy)
        x0, y0 = ix - n // 2, iy - n // 2
        ny, nx = image.shape
        a0, a1 = max(x0, xmin), min(x0 + n, xmin + nx)
        b0, b1 = max(y0, ymin), min(y0 + n, ymin + ny)
        if a0 >= a1 or b0 >= b1:
            return False
        st = self.stamp(n, x - ix, y - iy, flux, profile)
        image[b0 - ymin:b1 - ymin, a0 - xmin:a1 - xmin] += st[b0 - y0:b1 - y0, a0 - x0:a1 - x0]
        return True


def star_stamp_size(flux: float) -> int:
    """Stamp side for a point source, a power of two from 16 to 2048, growing as flux^(1/3).

    The halo of the Roman PSF falls as r^-3, so this keeps the edge of the
    stamp near a fixed level (~1 e-/pixel, far below where persistence
    matters) while the diffraction spikes of bright stars, which cause their
    ghosts, stay inside: 64 pixels for 1e5 e-, 16 for 1.6e3 e- and fainter
    (a J129 = 24 star leaves ~0.1 e-/pixel at the edge of its 16-pixel
    stamp; the 4% of its light beyond wraps into the stamp's edges).  A
    larger floor would only spread the faint stars' light, and with it their
    persistence, over pixels where it is a thousandth of an electron.
    """
    n = 64.0 * (max(flux, 1.0) / 1.0e5) ** (1.0 / 3.0)
    return int(min(2048, max(16, 2 ** math.ceil(math.log2(n)))))


def galaxy_stamp_size(hlr_pixels: float) -> int:
    """Stamp side for a galaxy: ~12 half-light radii plus the PSF core, a power of two >= 64.

    Powers of two keep the number of tabulated PSF transfers small (one per size).
    """
    n = 12.0 * hlr_pixels + 24.0
    return int(max(64, 2 ** math.ceil(math.log2(n))))
