"""Regions of the sky made of detector footprints: convex spherical polygons and their union.

A detector footprint (:func:`perscli.scene.footprints.sca_footprint`) is a
quadrilateral whose corners are on the sky and whose sides are taken as
great-circle arcs.  (For a Roman SCA the true edge, through GalSim's TAN-SIP
WCS, departs from the arc between its corners by less than 0.001 arcsec.)
Great circles are straight lines on any gnomonic (TAN) tangent plane, so on
such a plane a footprint is exactly a convex polygon, and everything here
is done there:

- :func:`polygon_area`: the solid angle of one convex polygon (the sum of
  its fan of spherical triangles, Van Oosterom & Strackee's formula);
- :func:`polygon_meets_circle`: whether a polygon overlaps a cap (a circle
  of great-circle radius r is the circle of radius tan r on the plane
  tangent at its centre, so the test is exact);
- :func:`expand_polygon`: a polygon grown outwards by a margin (each side
  moved out by the margin, corners mitred: the result contains every point
  within the margin of the polygon);
- :class:`FootprintUnion`: the union of footprints, with
  :meth:`~FootprintUnion.contains`, its solid angle
  (:attr:`~FootprintUnion.area`) and a Poisson process of a given density on
  it (:meth:`~FootprintUnion.poisson_positions`).

The Poisson process is drawn on the bounding box of the union on the tangent
plane (a box whose solid angle has a closed form) and kept where it falls in
the union: a Poisson process restricted to a sub-region is a Poisson process
of the same density there, so the density per unit solid angle is exact
whatever the shape of the union, and no area enters the counts.
"""

from __future__ import annotations

import math

import numpy as np

from .. import PerscliError
from . import deproject, project, separation, unit_vector

#: arcmin^2 per steradian
ARCMIN2_PER_SR = (180.0 * 60.0 / math.pi) ** 2

#: the farthest a footprint corner may be from the tangent point of a union, degrees: beyond, the
#: gnomonic plane stretches so much that the bounding box wastes most of its draws
MAX_SPREAD_DEG = 60.0

#: Gauss-Legendre nodes per slab when integrating the area of a union, and slabs per footprint width
_AREA_NODES = 16
_AREA_SUBSLABS = 64


def rectangle_solid_angle(x1: float, x2: float, y1: float, y2: float) -> float:
    """Solid angle (sr) of the rectangle [x1, x2] x [y1, y2] of the gnomonic plane.

    The area element of the sphere on the plane is (1 + x^2 + y^2)^(-3/2) dx dy,
    whose integral from the origin to (x, y) is atan(x y / sqrt(1 + x^2 + y^2)).
    """
    def f(x, y):
        return math.atan(x * y / math.sqrt(1.0 + x * x + y * y))

    return f(x2, y2) - f(x1, y2) - f(x2, y1) + f(x1, y1)


def _check_corners(ra, dec, what: str = "footprint") -> tuple:
    ra = np.asarray(ra, dtype=np.float64).reshape(-1)
    dec = np.asarray(dec, dtype=np.float64).reshape(-1)
    if ra.shape != dec.shape or ra.size < 3:
        raise PerscliError(f"{what}: give its corners as two sequences (RA, Dec) of at least 3 values each, "
                           f"not {ra.size} and {dec.size}")
    if not (np.all(np.isfinite(ra)) and np.all(np.isfinite(dec)) and np.all(np.abs(dec) <= 90.0)):
        raise PerscliError(f"{what}: corners must be finite, in degrees, with Dec in [-90, 90]")
    return ra % 360.0, dec


def polygon_centre(ra, dec) -> tuple:
    """The direction of the mean of the corners' unit vectors, (ra, dec) in degrees."""
    v = unit_vector(np.asarray(ra, dtype=np.float64), np.asarray(dec, dtype=np.float64)).reshape(-1, 3).sum(axis=0)
    norm = np.linalg.norm(v)
    if norm == 0:
        raise PerscliError("footprint corners cancel out: they do not describe a region of the sky")
    v /= norm
    return float(np.degrees(np.arctan2(v[1], v[0])) % 360.0), float(np.degrees(np.arcsin(np.clip(v[2], -1, 1))))


def _ccw(x, y) -> tuple:
    """The polygon's vertices counter-clockwise (positive shoelace area) on the plane."""
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    return (x, y) if area >= 0 else (x[::-1], y[::-1])


def _check_convex(x, y, what: str):
    """Refuse a degenerate or non-convex polygon (vertices already counter-clockwise)."""
    dx, dy = np.roll(x, -1) - x, np.roll(y, -1) - y
    cross = dx * np.roll(dy, -1) - dy * np.roll(dx, -1)
    scale = np.hypot(dx, dy).max() ** 2
    if not scale > 0 or np.any(cross < -1e-12 * scale) or cross.sum() <= 1e-9 * scale:
        raise PerscliError(f"{what}: its corners do not make a convex polygon with a non-zero area "
                           "(give them in order around it)")


def polygon_area(ra, dec) -> float:
    """Solid angle (sr) of a convex spherical polygon with these corners (degrees), in order.

    The sum over the fan of triangles (v0, vi, vi+1) of
    2 atan(|v0 . (vi x vi+1)| / (1 + v0.vi + vi.vi+1 + vi+1.v0)), the exact
    solid angle of each spherical triangle (Van Oosterom & Strackee 1983).
    """
    ra, dec = _check_corners(ra, dec, "polygon")
    v = unit_vector(ra, dec)
    total = 0.0
    for i in range(1, len(v) - 1):
        a, b, c = v[0], v[i], v[i + 1]
        num = abs(float(np.dot(a, np.cross(b, c))))
        den = 1.0 + float(np.dot(a, b) + np.dot(b, c) + np.dot(c, a))
        total += 2.0 * math.atan2(num, den)
    return total


def polygon_meets_circle(ra, dec, ra0: float, dec0: float, radius: float) -> bool:
    """Whether a convex polygon (corners in degrees, in order) overlaps the cap of ``radius`` degrees.

    On the plane tangent at the cap's centre the cap is the disc of radius
    tan(radius) and the polygon's sides are straight: they overlap when the
    centre is inside the polygon or a side comes within tan(radius) of it.
    Caps of 90 degrees or more contain a hemisphere: any corner within
    ``radius`` of the centre then suffices, else the sides are checked on
    the sphere.
    """
    ra, dec = _check_corners(ra, dec)
    if radius >= 90.0:
        return bool(np.any(separation(ra0, dec0, ra, dec) <= radius))
    x, y = project(ra0, dec0, ra, dec)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        # a corner 90 degrees or more away: the polygon reaches round the sphere from this centre;
        # footprints are far smaller than that, so only a polygon far from a small cap gets here
        return bool(np.any(separation(ra0, dec0, ra, dec) <= radius))
    x, y = _ccw(x, y)
    r = math.tan(math.radians(radius))
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    dx, dy = x1 - x, y1 - y
    # the centre (origin) inside: on the left of every side
    if np.all(dx * (0.0 - y) - dy * (0.0 - x) >= 0):
        return True
    # distance from the origin to each side (segment)
    length2 = dx * dx + dy * dy
    t = np.clip(np.where(length2 > 0, -(x * dx + y * dy) / np.where(length2 > 0, length2, 1.0), 0.0), 0.0, 1.0)
    d2 = (x + t * dx) ** 2 + (y + t * dy) ** 2
    return bool(np.any(d2 <= r * r))


def expand_polygon(ra, dec, margin_arcsec: float) -> tuple:
    """A convex polygon grown outwards by ``margin_arcsec`` on every side.

    Done on the plane tangent at the polygon's centre (over a Roman SCA the
    plane's scale departs from the sphere's by less than 1e-5): each side
    moves out by the margin and each corner goes to where its two moved
    sides meet (a mitred corner, further out than the margin, so that every
    point within the margin of the polygon is inside the result).

    Returns
    -------
    ra, dec : ndarray
        The new corners, degrees, in the given order.
    """
    ra, dec = _check_corners(ra, dec)
    if not (math.isfinite(margin_arcsec) and margin_arcsec >= 0):
        raise PerscliError(f"margin {margin_arcsec} arcsec: must be a number >= 0")
    if margin_arcsec == 0:
        return ra.copy(), dec.copy()
    ra0, dec0 = polygon_centre(ra, dec)
    x, y = project(ra0, dec0, ra, dec)
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    sign = 1.0 if area >= 0 else -1.0
    dx, dy = np.roll(x, -1) - x, np.roll(y, -1) - y
    length = np.hypot(dx, dy)
    if np.any(length == 0):
        raise PerscliError("footprint: two corners coincide; give distinct corners in order around it")
    # outward normal of side i (from corner i to i+1): to the right of a counter-clockwise polygon
    nx, ny = sign * dy / length, -sign * dx / length
    px, py = np.roll(nx, 1), np.roll(ny, 1)          # the side that ends at corner i
    m = math.tan(math.radians(margin_arcsec / 3600.0))
    k = m / (1.0 + nx * px + ny * py)
    return deproject(ra0, dec0, x + k * (nx + px), y + k * (ny + py))


class FootprintUnion:
    """The union of convex footprints on the sky.

    Parameters
    ----------
    footprints : sequence of (ra, dec)
        Corners of each footprint in degrees, in order around it (e.g.
        :func:`perscli.scene.footprints.sca_footprint`).
    margin_arcsec : float
        Each footprint is grown by this much (:func:`expand_polygon`).
    centre : (float, float), optional
        Tangent point of the plane the union is handled on; default the
        direction of the mean of every corner.

    Raises
    ------
    PerscliError
        No footprint, corners that are not finite or not in order around a
        convex polygon, or footprints spread over more than
        :data:`MAX_SPREAD_DEG` from the centre.
    """

    def __init__(self, footprints, margin_arcsec: float = 0.0, centre=None):
        footprints = list(footprints)
        if not footprints:
            raise PerscliError("no footprint given: a catalogue of footprints needs at least one")
        if not (math.isfinite(margin_arcsec) and margin_arcsec >= 0):
            raise PerscliError(f"margin {margin_arcsec} arcsec: must be a number >= 0")
        self.margin_arcsec = float(margin_arcsec)
        given = []
        for k, item in enumerate(footprints, 1):
            try:
                ra, dec = item
            except (TypeError, ValueError):
                raise PerscliError(f"footprint {k}: give it as (ra corners, dec corners)") from None
            given.append(_check_corners(ra, dec, f"footprint {k}"))
        self.given = given
        self.polygons = [expand_polygon(ra, dec, self.margin_arcsec) for ra, dec in given]
        if centre is None:
            centre = polygon_centre(np.concatenate([p[0] for p in self.polygons]),
                                    np.concatenate([p[1] for p in self.polygons]))
        self.ra, self.dec = float(centre[0]) % 360.0, float(centre[1])
        if not (math.isfinite(self.ra) and -90.0 <= self.dec <= 90.0):
            raise PerscliError(f"centre ({centre[0]}, {centre[1]}): give RA in degrees and Dec in [-90, 90]")
        limit = math.tan(math.radians(MAX_SPREAD_DEG))
        xs, ys = [], []
        for k, (ra, dec) in enumerate(self.polygons, 1):
            x, y = project(self.ra, self.dec, ra, dec)
            if not (np.all(np.isfinite(x)) and np.all(np.hypot(x, y) <= limit)):
                raise PerscliError(f"footprint {k} lies more than {MAX_SPREAD_DEG:g} degrees from ({self.ra:.6g}, "
                                   f"{self.dec:.6g}): make one catalogue per region of the sky")
            x, y = _ccw(x, y)
            _check_convex(x, y, f"footprint {k}")
            xs.append(x)
            ys.append(y)
        self._x = np.array(xs)
        self._y = np.array(ys)
        self.box = (float(self._x.min()), float(self._x.max()), float(self._y.min()), float(self._y.max()))
        self._area = None

    def __len__(self) -> int:
        return len(self.polygons)

    # -- membership ------------------------------------------------------------------------
    def contains(self, ra, dec) -> np.ndarray:
        """Which positions (degrees) lie in the union (edges included)."""
        ra = np.asarray(ra, dtype=np.float64)
        dec = np.asarray(dec, dtype=np.float64)
        x, y = project(self.ra, self.dec, ra.reshape(-1), dec.reshape(-1))
        return self._contains_xy(x, y).reshape(ra.shape)

    def _contains_xy(self, x, y) -> np.ndarray:
        inside = np.zeros(x.shape, dtype=bool)
        ok = np.isfinite(x) & np.isfinite(y)
        order = np.argsort(np.where(ok, x, np.inf), kind="stable")
        xs = np.where(ok, x, np.inf)[order]
        # one polygon at a time, on the points of its x range only: each footprint is small
        # against the union, so this costs about (points per footprint) x (footprints)
        for px, py in zip(self._x, self._y):
            lo = np.searchsorted(xs, px.min(), side="left")
            hi = np.searchsorted(xs, px.max(), side="right")
            if hi <= lo:
                continue
            idx = order[lo:hi]
            cy = y[idx]
            # points already inside an earlier footprint need no further test
            near = (cy >= py.min()) & (cy <= py.max()) & ~inside[idx]
            idx, cx, cy = idx[near], x[idx][near], cy[near]
            if idx.size == 0:
                continue
            good = np.ones(idx.size, dtype=bool)
            for i in range(len(px)):
                j = (i + 1) % len(px)
                good &= (px[j] - px[i]) * (cy - py[i]) - (py[j] - py[i]) * (cx - px[i]) >= 0
            inside[idx[good]] = True
        return inside

    # -- area ---------------------------------------------------------------------------------
    @property
    def area(self) -> float:
        """Solid angle of the union in arcmin^2.

        The integral of the sphere's area element (1 + x^2 + y^2)^(-3/2)
        over the union on the tangent plane: between consecutive corner
        abscissae every footprint is cut by a vertical line in one interval
        whose ends move linearly, and the covered length of each line (the
        union of those intervals, each weighted in closed form) is
        integrated with 16-point Gauss-Legendre on slabs at most 1/64 of the
        narrowest footprint wide.  Exact to rounding for footprints that do
        not overlap; where sides of overlapping footprints cross inside a
        slab the integrand has a kink, and the relative error is ~1e-7 (two
        SCA footprints crossing, against their exact overlap).  The counts
        of a catalogue do not depend on it (:meth:`poisson_positions`).
        """
        if self._area is None:
            self._area = self._union_area() * ARCMIN2_PER_SR
        return self._area

    def _union_area(self) -> float:
        px, py = self._x, self._y
        x0, y0 = px, py
        x1, y1 = np.roll(px, -1, axis=1), np.roll(py, -1, axis=1)
        breaks = np.unique(px)
        # where sides of different footprints cross inside a slab the covered length has a kink, which
        # Gauss-Legendre integrates to O(h^2): slabs no wider than 1/64 of the narrowest footprint keep
        # that below ~1e-7 of the area (finding every crossing would cost (sides)^2)
        width = float((px.max(axis=1) - px.min(axis=1)).min()) / _AREA_SUBSLABS
        if width > 0:
            pieces = [np.linspace(a, b, int(math.ceil((b - a) / width)) + 1)[:-1] for a, b in zip(breaks[:-1],
                                                                                             breaks[1:])]
            breaks = np.concatenate(pieces + [breaks[-1:]])
        nodes, weights = np.polynomial.legendre.leggauss(_AREA_NODES)
        pmin, pmax = px.min(axis=1), px.max(axis=1)
        total = 0.0
        for a, b in zip(breaks[:-1], breaks[1:]):
            active = (pmin <= a) & (pmax >= b)
            if not active.any():
                continue
            xs = 0.5 * (a + b) + 0.5 * (b - a) * nodes                           # (n,)
            ax0, ay0, ax1, ay1 = x0[active], y0[active], x1[active], y1[active]  # (k, 4)
            X = xs[:, None, None]
            lo_e, hi_e = np.minimum(ax0, ax1), np.maximum(ax0, ax1)
            hit = (X >= lo_e) & (X <= hi_e) & (hi_e > lo_e)
            with np.errstate(divide="ignore", invalid="ignore"):
                yy = ay0 + (X - ax0) * (ay1 - ay0) / (ax1 - ax0)
            lo = np.where(hit, yy, np.inf).min(axis=2)                           # (n, k)
            hi = np.where(hit, yy, -np.inf).max(axis=2)
            order = np.argsort(lo, axis=1)
            lo = np.take_along_axis(lo, order, axis=1)
            hi = np.take_along_axis(hi, order, axis=1)
            reach = np.maximum.accumulate(hi, axis=1)
            before = np.concatenate([np.full((len(xs), 1), -np.inf), reach[:, :-1]], axis=1)
            start = np.maximum(lo, before)
            end = np.maximum(hi, start)
            q = 1.0 + xs * xs
            g = lambda v: v / (q[:, None] * np.sqrt(q[:, None] + v * v))   # noqa: E731
            covered = np.where(end > start, g(end) - g(np.where(np.isfinite(start), start, 0.0)), 0.0)
            total += 0.5 * (b - a) * float(np.dot(weights, covered.sum(axis=1)))
        return total

    # -- drawing ------------------------------------------------------------------------------
    @property
    def box_area(self) -> float:
        """Solid angle of the bounding box on the tangent plane, arcmin^2."""
        return rectangle_solid_angle(*self.box) * ARCMIN2_PER_SR

    def poisson_positions(self, rng: np.random.Generator, density: float) -> tuple:
        """A Poisson process of ``density`` per arcmin^2 on the union: (ra, dec) in degrees.

        Poisson(density x box area) points uniform in solid angle over the
        bounding box (uniform on the plane, kept with probability
        proportional to the sphere's area element), then those in the union.
        """
        x1, x2, y1, y2 = self.box
        n = int(rng.poisson(density * self.box_area))
        # the largest area element in the box, at its point nearest the tangent point
        cx, cy = min(max(0.0, x1), x2), min(max(0.0, y1), y2)
        w_max = (1.0 + cx * cx + cy * cy) ** -1.5
        accept = rectangle_solid_angle(x1, x2, y1, y2) / ((x2 - x1) * (y2 - y1) * w_max) if n else 1.0
        xs, ys = [], []
        have = 0
        while have < n:
            m = int((n - have) / accept * 1.05) + 16
            x = rng.uniform(x1, x2, m)
            y = rng.uniform(y1, y2, m)
            keep = rng.random(m) * w_max < (1.0 + x * x + y * y) ** -1.5
            xs.append(x[keep])
            ys.append(y[keep])
            have += int(keep.sum())
        x = np.concatenate(xs)[:n] if xs else np.empty(0)
        y = np.concatenate(ys)[:n] if ys else np.empty(0)
        inside = self._contains_xy(x, y)
        return deproject(self.ra, self.dec, x[inside], y[inside])
