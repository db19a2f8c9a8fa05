"""A closed race track given by its centre-line curvature ``κ(s)`` (thesis §8.4, SPEC §2.33).

The centre line is described by piecewise-constant curvature samples (segment lengths and
curvatures, e.g. straights ``κ = 0`` and arcs ``κ = 1/r``). Every jump of ``κ`` is replaced
by a linear ramp of length ``transition`` centred on the junction (a clothoid), so ``κ(s)``
is continuous — the continuous-curvature representation the thesis cites ([184]); the
ramps are symmetric, so the total turning ``∫κ ds`` is unchanged. ``κ(s)`` is available
on numbers (:meth:`Track.curvature`) and on CasADi symbols (:meth:`Track.kappa`, periodic
in ``s`` with period ``L``), so dynamics such as the Frenet model (8.5) can use it.

Conventions: ``s`` is the arc length along the centre line, ``n`` (called ``e`` in (8.5))
the signed lateral offset, positive to the *left* of the direction of travel, and ``μ`` the
heading relative to the centre-line tangent (positive = pointing left). ``κ > 0`` is a left
(counter-clockwise) turn. Then ``ṡ = (v_x cos μ − v_y sin μ)/(1 − nκ)`` as in (8.5).

:func:`oval` is the SPEC §3.8 default: two 2 m straights and two half circles of radius
0.6 m, track width 0.5 m. :func:`plot_track` draws a track and trajectories on a
matplotlib axis.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade._checks import as_scalar, as_vector
from balustrade.errors import BalustradeError, ShapeError

#: points per metre of the tabulated centre line (geometry, projections)
RESOLUTION = 2000


@dataclass
class Track:
    """A track from curvature samples, treated as closed: ``κ(s)``, the centre line and the
    projections are periodic in ``s`` with period ``L`` (:meth:`closure` says how well the
    samples actually close).

    ``lengths[j]`` (m, > 0) and ``curvatures[j]`` (1/m) describe segment ``j`` of constant
    curvature before smoothing; ``width`` is the full track width (the constraint of (8.6)
    is ``|n| <= width/2`` by the SPEC §2.33 default); ``transition`` the length of the
    curvature ramps (0: piecewise constant); ``start`` = ``(x, y, heading)`` of ``s = 0``.
    """

    lengths: np.ndarray
    curvatures: np.ndarray
    width: float = 0.5
    transition: float = 0.2
    start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = "track"
    _table: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.lengths = as_vector(self.lengths, f"{self.name}: lengths")
        self.curvatures = as_vector(self.curvatures, f"{self.name}: curvatures")
        if self.lengths.size != self.curvatures.size:
            raise ShapeError(f"{self.name}: curvatures", f"{self.lengths.size} entries "
                             "(one per segment length)", self.curvatures.shape)
        if self.lengths.size == 0 or np.any(self.lengths <= 0):
            raise BalustradeError(f"{self.name}: lengths must be positive, got {self.lengths}")
        self.width = as_scalar(self.width, f"{self.name}: width", low=0.0, low_open=True)
        self.transition = as_scalar(self.transition, f"{self.name}: transition", low=0.0)
        if self.transition > np.min(self.lengths):
            raise BalustradeError(f"{self.name}: transition {self.transition} is longer than "
                                  f"the shortest segment {np.min(self.lengths)}")
        start = as_vector(self.start, f"{self.name}: start (x, y, heading)", 3)
        self.start = (float(start[0]), float(start[1]), float(start[2]))
        self._tabulate()

    # -- curvature --------------------------------------------------------------------------
    @property
    def length(self) -> float:
        """Total arc length ``L``."""
        return float(np.sum(self.lengths))

    @property
    def junctions(self) -> np.ndarray:
        """Arc lengths where segment ``j`` starts (``j >= 1``; periodic: ``s = 0`` too)."""
        return np.concatenate([[0.0], np.cumsum(self.lengths)[:-1]])

    def _ramps(self) -> list[tuple[float, float]]:
        """``(junction s_j, jump Δκ_j)`` for every junction, incl. the wrap-around one
        (``j = 0``, at ``s = 0 ≡ L``, jump ``κ_0 − κ_{last}``)."""
        k = self.curvatures
        return [(float(s), float(k[j] - k[j - 1])) for j, s in enumerate(self.junctions)]

    def _kappa_with(self, r: object, ramp) -> object:
        """``κ_0 + Σ_{j>=1} Δκ_j ρ(r − s_j) + Δκ_0 (ρ(r) − 1 + ρ(r − L))`` for ``r`` in
        ``[0, L)``, ``ρ`` the unit ramp of length ``transition`` centred at 0."""
        L = self.length
        out = 0 * r + float(self.curvatures[0])
        for j, (sj, dk) in enumerate(self._ramps()):
            if dk == 0.0:
                continue
            if j == 0:
                out = out + dk * (ramp(r) - 1.0 + ramp(r - L))
            else:
                out = out + dk * ramp(r - sj)
        return out

    def kappa(self, s: object) -> object:
        """``κ(s)`` on CasADi symbols (or numbers), periodic with period ``L``: piecewise
        linear, one ramp ``Δκ_j·clip((s − s_j)/t + 1/2, 0, 1)`` per junction (a step if
        ``transition = 0``)."""
        if not isinstance(s, (ca.SX, ca.MX)):
            return self.curvature(s)
        t, L = self.transition, self.length
        if t == 0.0:
            def ramp(d: object) -> object:
                return ca.if_else(d >= 0, 1.0, 0.0)
        else:
            def ramp(d: object) -> object:
                return ca.fmin(ca.fmax(d / t + 0.5, 0.0), 1.0)
        return self._kappa_with(s - L * ca.floor(s / L), ramp)

    def curvature(self, s: object) -> np.ndarray | float:
        """``κ(s)`` on numbers (array in, array out), periodic with period ``L``."""
        arr = np.asarray(s, dtype=float)
        t = self.transition

        def ramp(d: np.ndarray) -> np.ndarray:
            return np.clip(d / t + 0.5, 0.0, 1.0) if t > 0 else (d >= 0).astype(float)

        out = self._kappa_with(np.mod(arr, self.length), ramp)
        return float(out) if np.ndim(s) == 0 else np.asarray(out, dtype=float)

    # -- geometry -------------------------------------------------------------------------
    def _tabulate(self) -> None:
        """Heading and centre line on a fine grid (trapezoid for ``ψ_c = ∫κ``, Simpson-like
        midpoint rule for the position); used by the conversions and the plots."""
        n = max(200, int(np.ceil(self.length * RESOLUTION)))
        s = np.linspace(0.0, self.length, n + 1)
        k = self.curvature(s)
        ds = np.diff(s)
        psi = self.start[2] + np.concatenate([[0.0], np.cumsum(0.5 * (k[1:] + k[:-1]) * ds)])
        # exact position increment for a linearly varying heading over a short step
        mid = 0.5 * (psi[1:] + psi[:-1])
        x = self.start[0] + np.concatenate([[0.0], np.cumsum(np.cos(mid) * ds)])
        y = self.start[1] + np.concatenate([[0.0], np.cumsum(np.sin(mid) * ds)])
        self._table = {"s": s, "x": x, "y": y, "psi": psi, "kappa": k}
        self._tree = None

    def centre(self, s: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centre-line position ``(x, y)`` and tangent heading ``ψ_c`` at ``s`` (interpolated
        on the table; ``s`` wraps around for a closed track)."""
        t = self._table
        s = np.mod(np.asarray(s, dtype=float), self.length)
        x, y = np.interp(s, t["s"], t["x"]), np.interp(s, t["s"], t["y"])
        psi = np.interp(s, t["s"], t["psi"])
        return x, y, psi

    def closure(self) -> dict[str, float]:
        """How well the track closes: total turning ``∫κ ds`` (``2π`` for one loop), the
        heading error ``∫κ ds − 2π·round(∫κ ds / 2π)`` and the gap between end and start."""
        t = self._table
        turning = float(t["psi"][-1] - t["psi"][0])
        turns = round(turning / (2 * np.pi))
        gap = float(np.hypot(t["x"][-1] - t["x"][0], t["y"][-1] - t["y"][0]))
        return {"turning": turning, "turns": float(turns),
                "heading_error": turning - 2 * np.pi * turns, "gap": gap}

    def is_closed(self, tol: float = 1e-6) -> bool:
        """``∫κ ds = ±2π`` (one loop) and the end meets the start, within ``tol``."""
        c = self.closure()
        return abs(c["turns"]) == 1 and abs(c["heading_error"]) <= tol and c["gap"] <= tol

    def to_frenet(self, x: object, y: object, psi: object
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cartesian ``(x, y, ψ)`` → Frenet ``(s, n, μ)``: ``s`` of the nearest centre-line
        point (table nearest neighbour, refined by projection on the local tangent),
        ``n`` the signed offset (left positive), ``μ = ψ − ψ_c(s)`` wrapped to ``(−π, π]``.
        Valid within ``|n| < 1/max κ`` of the centre line."""
        from scipy.spatial import cKDTree

        x, y, psi = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (x, y, psi))
        if not (x.shape == y.shape == psi.shape):
            raise ShapeError(f"{self.name}.to_frenet", "x, y, psi of equal shape",
                             (x.shape, y.shape, psi.shape), what="shapes")
        t = self._table
        if self._tree is None:
            self._tree = cKDTree(np.column_stack([t["x"][:-1], t["y"][:-1]]))
        _, idx = self._tree.query(np.column_stack([x, y]))
        s0, psi0 = t["s"][idx], t["psi"][idx]
        dx, dy = x - t["x"][idx], y - t["y"][idx]
        ds = dx * np.cos(psi0) + dy * np.sin(psi0)
        s = np.mod(s0 + ds, self.length)
        for _ in range(2):  # Newton steps on the tangential offset (curved centre line)
            cx, cy, cpsi = self.centre(s)
            along = (x - cx) * np.cos(cpsi) + (y - cy) * np.sin(cpsi)
            lat = -(x - cx) * np.sin(cpsi) + (y - cy) * np.cos(cpsi)
            s = np.mod(s + along / (1.0 - lat * self.curvature(s)), self.length)
        cx, cy, cpsi = self.centre(s)
        n = -(x - cx) * np.sin(cpsi) + (y - cy) * np.cos(cpsi)
        mu = np.angle(np.exp(1j * (psi - cpsi)))
        return s, n, mu

    def to_cartesian(self, s: object, n: object, mu: object
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frenet ``(s, n, μ)`` → Cartesian ``(x, y, ψ)``: ``p = c(s) + n·(−sin ψ_c, cos ψ_c)``
        and ``ψ = ψ_c(s) + μ``."""
        s, n, mu = (np.asarray(v, dtype=float) for v in (s, n, mu))
        cx, cy, cpsi = self.centre(s)
        return cx - n * np.sin(cpsi), cy + n * np.cos(cpsi), cpsi + mu

    def borders(self, samples: int = 1000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centre line, left and right border as ``(samples, 2)`` arrays."""
        s = np.linspace(0.0, self.length, samples)
        cx, cy, _ = self.centre(s)
        lx, ly, _ = self.to_cartesian(s, np.full_like(s, self.width / 2), np.zeros_like(s))
        rx, ry, _ = self.to_cartesian(s, np.full_like(s, -self.width / 2), np.zeros_like(s))
        return (np.column_stack([cx, cy]), np.column_stack([lx, ly]),
                np.column_stack([rx, ry]))


def oval(straight: float = 2.0, radius: float = 0.6, width: float = 0.5,
         transition: float = 0.2) -> Track:
    """The SPEC §3.8 default track: two straights of ``straight`` m and two half circles
    of radius ``radius`` (counter-clockwise, ``κ = 1/radius``), width ``width``, curvature
    ramps of ``transition`` m. ``s = 0`` is the start of the lower straight (mid-ramp), whose
    heading after the ramp is +x."""
    straight = as_scalar(straight, "oval: straight", low=0.0, low_open=True)
    radius = as_scalar(radius, "oval: radius", low=0.0, low_open=True)
    arc = np.pi * radius
    # s = 0 lies mid-ramp: start with heading −∫_0^{t/2} κ ds = −t/(8r), so that the straights
    # (after the ramp) are parallel to the x axis
    return Track(np.array([straight, arc, straight, arc]),
                 np.array([0.0, 1.0 / radius, 0.0, 1.0 / radius]), width=width,
                 transition=transition, start=(-straight / 2, -radius, -transition / (8 * radius)),
                 name="oval")


def plot_track(ax: object, track: Track, trajectories: object = (), color_by: object = None,
               cmap: str = "coolwarm", markers: object = None, label: str | None = None
               ) -> object:
    """Draw ``track`` (centre line dashed, borders solid) on a matplotlib axis and the
    trajectories (``(T, ≥2)`` arrays of Cartesian ``x, y``; several as a list). ``color_by``
    (one ``(T,)`` array per trajectory, e.g. the filter intervention ``‖u − u_p‖``) colours
    the trajectory; ``markers`` (``(M, 2)``) marks points (e.g. constraint violations) in
    red. Returns the colour collection of the last coloured trajectory (for a colour bar)."""
    from matplotlib.collections import LineCollection

    centre, left, right = track.borders()
    ax.plot(centre[:, 0], centre[:, 1], "--", color="0.6", lw=0.8)
    ax.plot(left[:, 0], left[:, 1], "k-", lw=1.2)
    ax.plot(right[:, 0], right[:, 1], "k-", lw=1.2)
    trajs = [trajectories] if isinstance(trajectories, np.ndarray) else list(trajectories)
    colors = ([color_by] if isinstance(color_by, np.ndarray) else
              (list(color_by) if color_by is not None else [None] * len(trajs)))
    if len(colors) != len(trajs):
        raise ShapeError("plot_track: color_by", f"{len(trajs)} arrays (one per trajectory)",
                         len(colors), what="count")
    last = None
    for traj, col in zip(trajs, colors):
        traj = np.asarray(traj, dtype=float)
        if traj.ndim != 2 or traj.shape[1] < 2:
            raise ShapeError("plot_track: trajectory", "(T, >=2) array of x, y", traj.shape)
        if col is None:
            ax.plot(traj[:, 0], traj[:, 1], lw=1.2, label=label)
            continue
        col = np.asarray(col, dtype=float).reshape(-1)
        if col.size != traj.shape[0]:
            raise ShapeError("plot_track: color_by", f"{traj.shape[0]} values", col.size)
        seg = np.stack([traj[:-1, :2], traj[1:, :2]], axis=1)
        last = LineCollection(seg, cmap=cmap, linewidths=1.8)
        last.set_array(col[:-1])
        ax.add_collection(last)
    if markers is not None and len(markers):
        m = np.asarray(markers, dtype=float)
        ax.plot(m[:, 0], m[:, 1], "o", mfc="none", mec="red", ms=9, mew=1.5)
    ax.set_aspect("equal")
    ax.autoscale_view()
    return last


__all__ = ["Track", "oval", "plot_track"]
