"""Roman's optics, the one home of what render and measure both draw with.

- :func:`bandpasses`, :func:`roman_wavelength`: GalSim's Roman filters (with
  their AB zeropoints) and their effective wavelengths;
- :func:`roman_psf`: GalSim's Roman PSF of an SCA and filter, with the
  project's settings (the PSF at the SCA centre and the filter's effective
  wavelength), made once a process; :func:`quick_roman_psf`, the coarser one
  of the sample frames; :func:`to_pixels`, a profile in Roman pixel units;
- :class:`StampDrawer` (with :func:`star_stamp_size`, :func:`galaxy_stamp_size`
  and the cache :func:`stamp_drawer`): objects drawn through a fixed PSF,
  exactly sampled, fast;
- :class:`Optics`: the WCS of an SCA for an exposure (``galsim.roman.getWCS``,
  through :func:`perscli.scene.footprints.sca_wcs`), its PSF, zeropoint and
  sky.

Why a module of its own: ``perscli render`` draws frames through this PSF and
``perscli measure --psf roman`` fits shapes through the same one, with the
same drawing code; with the PSF built here once, a frame and its fits cannot
drift apart, and measure does not reach into render.  It sits below render and
measure and imports neither.

Drawing: why not GalSim's ``Convolve(galaxy, psf).drawImage()`` per object: it
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

import functools
import math

import galsim
import galsim.roman as roman
import numpy as np
import scipy.fft
from galsim import fitswcs

from . import PerscliError, _kernels
from .instrument import ROMAN_SCA_SIZE
from .scene.footprints import sca_wcs, sky_to_pixels

# -- filters and the PSF --------------------------------------------------------------------------


@functools.lru_cache(maxsize=1)
def bandpasses() -> dict:
    """GalSim's Roman bandpasses with AB zeropoints (read from GalSim's files: ~0.25 s, so once a process)."""
    return roman.getBandpasses(AB_zeropoint=True)


def roman_wavelength(filt) -> float | None:
    """Effective wavelength (nm) of a Roman filter name, None for any other."""
    name = str(filt or "").strip()
    table = bandpasses()
    return float(table[name].effective_wavelength) if name in table else None


@functools.lru_cache(maxsize=8)
def roman_psf(sca: int, filter_name: str):
    """GalSim's Roman PSF of an SCA and filter at the filter's effective wavelength (sky units).

    It depends on nothing else (one PSF per SCA and filter, the one at the
    SCA centre), and ``galsim.roman.getPSF`` takes ~0.7 s: a process that
    renders many exposures (a study's worker), or measures many frames,
    makes it once per SCA and filter.
    """
    return roman.getPSF(int(sca), filter_name, wavelength=bandpasses()[filter_name].effective_wavelength)


def quick_roman_psf(sca: int, filter_name: str):
    """The sample frames' PSF (:mod:`perscli.samples`): :func:`roman_psf` from a pupil binned 8x (GalSim's
    default 4x), at the filter's effective wavelength.

    Coarser and quicker to make; the demo and the documentation's frames were
    drawn with it, so it stays as it is (their pixels would change).
    """
    return roman.getPSF(sca, filter_name, n_waves=5, pupil_bin=8, wavelength=bandpasses()[filter_name])


def to_pixels(profile):
    """A profile in sky units (arcsec) in Roman pixel units (``galsim.roman.pixel_scale``)."""
    return galsim.PixelScale(roman.pixel_scale).toImage(profile)


# -- drawing through the PSF ----------------------------------------------------------------------

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
        self._splits = {}

    @property
    def nbytes(self) -> int:
        """Bytes held by the tables made so far."""
        return sum(t.nbytes + k.nbytes for t, k in self._tables.values()) + \
            sum(a.nbytes + b.nbytes + k.nbytes for a, b, k in self._splits.values())

    def table(self, n: int):
        """(T, k) for stamp size n: PSF x pixel transfer (PSF only without ``pixel``) on the extended grid,
        and the frequencies."""
        table = self._tables.get(n)
        if table is None:
            table = self._tables[n] = self._transfer(n)
        return table

    def _transfer(self, n: int):
        m = self.alias
        k = _centred_freqs(n, m)
        psf_k = self.psf.drawKImage(nx=m * n, ny=m * n, scale=2.0 * np.pi / n).array
        if self.pixel:
            pix = np.sinc(k / (2.0 * np.pi))
            return psf_k * pix[:, None] * pix[None, :], k
        return psf_k, k

    def _split(self, n: int):
        """The PSF transfer of side n as two contiguous float64 planes and the frequencies (for the kernel)."""
        split = self._splits.get(n)
        if split is None:
            # the complex table is kept only if something asked for it (a 2048-pixel star's is 270 MB)
            transfer, k = self._tables[n] if n in self._tables else self._transfer(n)
            split = self._splits[n] = (np.ascontiguousarray(transfer.real), np.ascontiguousarray(transfer.imag),
                                       np.ascontiguousarray(k, dtype=np.float64))
        return split

    def batch(self, n: int, dx, dy, forms=None, roll: bool = True) -> np.ndarray:
        """Stamps of unit flux for several objects of one stamp side: points, or exponential galaxies.

        The Fourier transform of each object (1 for a point; for an
        exponential of scale radius r0 seen through the Jacobian of the
        detector, 1 / (1 + k^T C k)^(3/2) with C its covariance form in
        pixel^2, :func:`exponential_forms`) times the tabulated PSF, the
        phase of its sub-pixel centre and the fold onto the sampled band, in
        one compiled pass per object (:func:`perscli._kernels.fold_objects`),
        then one batched inverse FFT: the pixel values of :meth:`stamp`
        without a Python step per object.

        Parameters
        ----------
        n : int
            Stamp side (even).
        dx, dy : array_like
            Sub-pixel offsets of the centres from (n/2, n/2), pixels.
        forms : ndarray, shape (B, 3), optional
            Per object (Cxx, Cxy, Cyy) of an exponential, or NaN in a row
            for a point; None: all points.
        roll : bool
            False: the stamps as the inverse FFT leaves them, the centre's
            pixel at [0, 0] (:func:`perscli._kernels.add_stamps` adds them so).

        Returns
        -------
        ndarray, shape (B, n, n)
        """
        dx = np.atleast_1d(np.asarray(dx, dtype=np.float64))
        dy = np.atleast_1d(np.asarray(dy, dtype=np.float64))
        params = np.zeros((len(dx), 6))
        params[:, 0], params[:, 1] = dx, dy
        if forms is not None:
            forms = np.asarray(forms, dtype=np.float64).reshape(len(dx), 3)
            galaxy = np.all(np.isfinite(forms), axis=1)
            params[galaxy, 2:5] = forms[galaxy]
            params[:, 5] = galaxy
        tr_re, tr_im, k = self._split(n)
        m, half = self.alias, n // 2 + 1
        spec = np.empty((len(dx), n, half), dtype=np.complex128)
        work = np.empty(2 * (2 * m * n + n * half))
        _kernels.fold_objects(spec, work, tr_re, tr_im, k, n, m, params)
        images = scipy.fft.irfft2(spec, s=(n, n), axes=(-2, -1))
        if not roll:
            return images
        # stamp index [n/2, n/2] is the centre's pixel
        return np.roll(images, (n // 2, n // 2), axis=(-2, -1))

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
        if profile is None:
            # a point: as :meth:`batch` draws it (the same values as the frames' stars)
            return self.batch(n, [dx], [dy])[0] * flux
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


def local_jacobians(wcs, x, y) -> np.ndarray:
    """The WCS Jacobian d(u, v)/d(x, y) (arcsec per pixel) at image positions: shape (N, 2, 2).

    ``wcs.local(PositionD(x, y))`` of GalSim's ``GSFitsWCS`` (the Roman
    WCS: SIP distortion, CD matrix, gnomonic projection) for many positions
    at once, by the same chain of Jacobians; u to the West, v to the North.
    Other WCS types go through GalSim one position at a time.
    """
    x = np.atleast_1d(np.asarray(x, dtype=np.float64))
    y = np.atleast_1d(np.asarray(y, dtype=np.float64))
    if type(wcs) is not fitswcs.GSFitsWCS or wcs.pv is not None:
        out = np.empty((len(x), 2, 2))
        for i, (xx, yy) in enumerate(zip(x, y)):
            out[i] = wcs.local(galsim.PositionD(float(xx), float(yy))).getMatrix()
        return out
    n = len(x)
    jac = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    px, py = x - wcs.crpix[0], y - wcs.crpix[1]
    if wcs.ab is not None:
        order = len(wcs.ab[0]) - 1
        powers = np.arange(order + 1)
        xpow, ypow = px[:, None] ** powers, py[:, None] ** powers
        dxpow = np.zeros_like(xpow)
        dypow = np.zeros_like(ypow)
        dxpow[:, 1:] = (powers[:-1] + 1.0) * xpow[:, :-1]
        dypow[:, 1:] = (powers[:-1] + 1.0) * ypow[:, :-1]
        # ab[c, i, j] multiplies x^i y^j in component c
        p1 = np.einsum("cij,ni,nj->nc", wcs.ab, xpow, ypow)
        j1 = np.stack([np.einsum("cij,ni,nj->nc", wcs.ab, dxpow, ypow),
                       np.einsum("cij,ni,nj->nc", wcs.ab, xpow, dypow)], axis=2)
        jac = j1 @ jac
    else:
        p1 = np.stack([px, py], axis=1)
    p2 = p1 @ np.asarray(wcs.cd).T
    jac = np.asarray(wcs.cd) @ jac
    unit = np.array([-1.0, 1.0]) * (galsim.degrees / galsim.radians)
    p2 = p2 * unit
    jac = jac * unit[None, :, None]
    j2 = wcs.center.jac_deproject_rad(p2[:, 0], p2[:, 1], projection=wcs.projection)
    jac = np.moveaxis(j2, -1, 0) @ jac
    return jac * (galsim.radians / galsim.arcsec)


#: hlr / scale radius of an exponential profile (GalSim's Exponential)
EXP_HLR_PER_SCALE = 1.6783469900166605


def exponential_forms(jac, hlr, g1, g2) -> np.ndarray:
    """The covariance forms (Cxx, Cxy, Cyy), pixel^2, of sheared exponentials seen through WCS Jacobians.

    An exponential of half-light radius ``hlr`` (arcsec) sheared by (g1, g2)
    (GalSim's ``Exponential(half_light_radius=hlr).shear(g1=g1, g2=g2)``) has
    the Fourier transform 1 / (1 + q^T S^2 q r0^2)^(3/2) on the sky (S the
    shear matrix, r0 the scale radius); through the detector's Jacobian J
    (:func:`local_jacobians`, sky per pixel) it is 1 / (1 + k^T C k)^(3/2) in
    pixel frequencies with C = r0^2 J^-1 S^2 J^-T.

    Returns
    -------
    ndarray, shape (N, 3)
    """
    jac = np.asarray(jac, dtype=np.float64).reshape(-1, 2, 2)
    g1, g2 = np.asarray(g1, dtype=np.float64), np.asarray(g2, dtype=np.float64)
    r0 = np.asarray(hlr, dtype=np.float64) / EXP_HLR_PER_SCALE
    norm = 1.0 / np.sqrt(1.0 - g1 * g1 - g2 * g2)
    shear = np.empty((len(r0), 2, 2))
    shear[:, 0, 0], shear[:, 0, 1] = norm * (1.0 + g1), norm * g2
    shear[:, 1, 0], shear[:, 1, 1] = norm * g2, norm * (1.0 - g1)
    inv = np.linalg.inv(jac)
    a = inv @ shear
    c = (a @ np.swapaxes(a, 1, 2)) * (r0 * r0)[:, None, None]
    return np.stack([c[:, 0, 0], c[:, 0, 1], c[:, 1, 1]], axis=1)


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
    """Stamp side for a galaxy: ~8 half-light radii plus the PSF core, a power of two >= 64.

    The stamp is periodic: what lies beyond its half-width comes back in at
    the other side.  An exponential of half-light radius h holds all but
    2.6e-4 of its light within 6.4 h, the half-width 4 h + 12 pixels reaches
    for h <= 5 pixels (0.55"), and the PSF's wings beyond the 32 pixels of
    the smallest stamp are the same for every object.  Powers of two keep the
    number of tabulated PSF transfers small (one per size).
    """
    n = 8.0 * hlr_pixels + 24.0
    return int(max(64, 2 ** math.ceil(math.log2(n))))


#: the stamp drawers kept by :func:`stamp_drawer`: their PSF tables of large stamps are the costly part
#: of drawing a bright star (2.2 s for the 1024 and 2048 tables, ~0.35 GB): drawers are kept, least
#: recently used dropped first, while their tables hold less than this many bytes (a study's earlier
#: exposures come in every filter)
_DRAWERS: dict = {}
_DRAWER_BYTES = 1.5e9


def stamp_drawer(sca: int, filter_name: str) -> StampDrawer:
    """The :class:`StampDrawer` of an SCA and filter's PSF, kept with its tables for later exposures."""
    key = (int(sca), filter_name)
    drawer = _DRAWERS.pop(key, None)
    if drawer is None:
        drawer = StampDrawer(to_pixels(roman_psf(sca, filter_name)))
    _DRAWERS[key] = drawer          # most recently used last
    while len(_DRAWERS) > 1 and sum(d.nbytes for d in _DRAWERS.values()) > _DRAWER_BYTES:
        _DRAWERS.pop(next(iter(_DRAWERS)))
    return drawer


# -- one exposure's optics ------------------------------------------------------------------------

class Optics:
    """WCS, PSF, zeropoint and sky of one exposure (the GalSim Roman objects).

    The PSF is made when first asked for (``psf_world``, ``psf_pixels``):
    where objects land (``perscli render --dry-run``) needs only the WCS.

    Parameters
    ----------
    exposure : perscli.render.exposure.Exposure
        Or anything with its ``ra``, ``dec``, ``pa``, ``mjd``, ``sca``,
        ``filter``, ``exptime`` and ``date``.
    """

    def __init__(self, exposure):
        self.exposure = exposure
        self.bandpass = bandpasses()[exposure.filter]
        # getWCS, with a clear error for a position Roman cannot observe at that date
        self.wcs = sca_wcs(exposure, exposure.sca)
        self.zeropoint = self.bandpass.zeropoint
        self.electrons_per_unit_flux = roman.collecting_area * exposure.exptime
        self.centre = galsim.PositionD(ROMAN_SCA_SIZE / 2 + 0.5, ROMAN_SCA_SIZE / 2 + 0.5)
        self.world_centre = self.wcs.toWorld(self.centre)

    @functools.cached_property
    def psf_world(self):
        """GalSim's Roman PSF of the SCA and filter, at the filter's effective wavelength (sky units)."""
        return roman_psf(self.exposure.sca, self.exposure.filter)

    @functools.cached_property
    def psf_pixels(self):
        """The PSF in pixel units (0.11" pixels)."""
        return to_pixels(self.psf_world)

    def electrons(self, mag) -> np.ndarray:
        """Expected electrons over the exposure for AB magnitudes in this filter."""
        return 10.0 ** (-0.4 * (np.asarray(mag, dtype=np.float64) - self.zeropoint)) * self.electrons_per_unit_flux

    def sky_rate(self) -> float:
        """Zodiacal (at the SCA centre, on the exposure's date) plus thermal background, e-/pixel/s.

        Raises
        ------
        PerscliError
            GalSim's sky table has no value there (too close to the Sun).
        """
        try:
            # the date places the Sun; without it GalSim puts the Sun at the vernal equinox
            zodi = roman.getSkyLevel(self.bandpass, world_pos=self.world_centre, exptime=1.0,
                                     date=self.exposure.date)
        except galsim.GalSimError as exc:
            e = self.exposure
            raise PerscliError(f"GalSim's Roman sky level at SCA {e.sca} (ra={self.world_centre.ra.deg:.5f} "
                               f"dec={self.world_centre.dec.deg:.5f}) on MJD {e.mjd:.5f}: "
                               f"{str(exc).splitlines()[0]}; choose another date (--mjd)") from None
        return float(zodi * self.wcs.pixelArea(self.centre) + roman.thermal_backgrounds[self.exposure.filter])

    def positions(self, ra_deg, dec_deg):
        """Image positions (x, y) of sky positions, GalSim convention (pixel centres at integers).

        NaN for positions too far from the SCA to land on it
        (:func:`perscli.scene.footprints.sky_to_pixels`).
        """
        return sky_to_pixels(self.wcs, ra_deg, dec_deg)
