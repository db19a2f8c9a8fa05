"""The parameter-set updates of SPEC §2.19: exact (4.7), fixed shape (box), hypercube.

* :class:`ExactUpdate`: ``Θ_k = Θ_{k−1} ∩ Δ_k``, a polytope; by default its redundant rows
  are removed after each update (one LP each; ``prune=False`` keeps them: rows grow with
  ``k``);
* :class:`FixedShapeUpdate`: ``Θ_k = {H_θ θ <= h_{θ,k}}`` with the rows of Θ₀ and
  ``h_{θ,k}[r] = max {H_θ[r] θ : θ ∈ Θ_{k−1} ∩ Δ_k}``, one LP per row;
  :class:`BoxUpdate` is the axis-aligned box (``2q`` LPs, the thesis' "2p" is a typo) used
  in the §4.7 example; the row LPs share one feasible set and are solved side by side in one
  HiGHS run (:func:`~balustrade.backends.lp.solve_lps_joint`), and none at all when the box
  Θ_{k−1} lies inside Δ_k (nothing learned, Θ_{k−1} returned);
* :class:`HypercubeUpdate`: ``Θ_k = B_∞(θ̄_k, η_k)`` with the nesting-preserving centre of
  SPEC §2.19 (:func:`hypercube_centre`); ``centre="naive"`` centres the cube on the bounding
  box instead, which can leave Θ_{k−1} — the base loop then refuses it (not nested).
"""

from __future__ import annotations

from functools import lru_cache
from itertools import combinations
from math import comb

import numpy as np

from balustrade._checks import as_scalar
from balustrade.backends.lp import is_feasible, solve_lp, solve_lps_joint
from balustrade.backends.solution import Status
from balustrade.dsl.sets import Box, Polytope
from balustrade.dsl.sets_geometry import verified_upper
from balustrade.dsl.system_parametric import ParametricLinearSystem
from balustrade.errors import BalustradeError
from balustrade.estimate.base import Proposal, SetEstimator, Transition, require_box
from balustrade.estimate.records import UpdateStatus

#: outward margin added to every LP bound before clipping to Θ_{k−1}: θ* on the boundary of
#: Δ_k (a vertex disturbance) must not be cut off by the LP's rounding
MARGIN = 1e-9


def _falsified(lps: int) -> Proposal:
    return Proposal(None, lps, UpdateStatus.FALSIFIED,
                    "Δ_k ∩ Θ_{k−1} is empty: the transition is inconsistent with W and "
                    "Θ_{k−1} (model falsified); Θ_{k−1} kept")


def _failed(lps: int, status: Status, what: str) -> Proposal:
    return Proposal(None, lps, UpdateStatus.FAILED,
                    f"{what} ended {status.value}; Θ_{{k−1}} kept")


class ExactUpdate(SetEstimator):
    """``Θ_k = Θ_{k−1} ∩ Δ_k`` (exact update of SPEC §2.19). ``prune`` (default True)
    removes the redundant rows after each update (one LP per row): the same set (equal by
    LPs at every step of the 3-mass RAPSF loop, ``benchmarks/exact_update_prune.py``) with a
    bounded number of rows; ``prune=False`` keeps every row, so the rows and the per-step
    cost of the vertex enumeration grow with ``k`` (docs/adaptive.md, session 14: 892 rows
    after 150 steps, 80 ms per step against 35 ms pruned at the end)."""

    def __init__(self, system: ParametricLinearSystem, W: Polytope, Theta0: Polytope,
                 prune: bool = True, name: str = "exact_update"):
        super().__init__(system, W, Theta0, name=name)
        self.prune = bool(prune)

    def propose(self, Theta_prev: Polytope, data: Transition) -> Proposal:
        both = data.delta.intersect(Theta_prev)
        status = is_feasible(both.H, both.h)
        if status is Status.INFEASIBLE:
            return _falsified(1)
        if status is not Status.OPTIMAL:
            return _failed(1, status, "the feasibility LP of Δ_k ∩ Θ_{k−1}")
        H, h, lps = both.H, both.h, 1
        if self.prune:
            H, h, extra = remove_redundant(H, h, keep=0)
            lps += extra
        return Proposal(Polytope(H, h, name=f"Theta_{self.k + 1}"), lps)


def remove_redundant(H: np.ndarray, h: np.ndarray, keep: int = 0,
                     tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray, int]:
    """Drop rows ``r >= keep`` implied by the others: ``max {H_r θ : other rows,
    H_r θ <= h_r + 1} <= h_r + tol`` (one LP per candidate row). Returns ``(H, h, lps)``."""
    rows = list(range(H.shape[0]))
    lps = 0
    for r in range(H.shape[0] - 1, keep - 1, -1):
        others = [i for i in rows if i != r]
        Hr = np.vstack([H[others], H[r]])
        hr = np.concatenate([h[others], [h[r] + 1.0]])
        res = solve_lp(H[r], Hr, hr)
        lps += 1
        if res.status is Status.OPTIMAL and res.value <= h[r] + tol:
            rows = others
    return H[rows], h[rows], lps


class FixedShapeUpdate(SetEstimator):
    """``Θ_k = {H_θ θ <= h_{θ,k}}`` with ``H_θ`` the rows of Θ₀ and
    ``h_{θ,k}[r] = max {H_θ[r] θ : θ ∈ Θ_{k−1} ∩ Δ_k}`` (one LP per row), clipped to
    ``h_{θ,k−1}`` so that nesting holds exactly."""

    def __init__(self, system: ParametricLinearSystem, W: Polytope, Theta0: Polytope,
                 margin: float = MARGIN, name: str = "fixed_shape_update"):
        super().__init__(system, W, Theta0, name=name)
        self.margin = as_scalar(margin, f"{name}: margin", low=0.0)

    def _support_bounds(self, Theta_prev: Polytope, data: Transition
                        ) -> tuple[np.ndarray | None, Proposal | None, int]:
        """``max H_θ[r] θ`` over ``Θ_{k−1} ∩ Δ_k`` for every row of Θ₀ (or a refusal):
        for a box ``Θ_{k−1}`` from the vertices of ``Θ_{k−1} ∩ Δ_k`` when they are few
        (:func:`vertex_supports`), else by the joint LPs; the last entry is the number of
        LPs solved."""
        both = data.delta.intersect(Theta_prev)
        if isinstance(Theta_prev, Box):             # verified bounds (box_supports)
            values, results = box_supports(self.Theta0.H, both.H, both.h, Theta_prev.lb,
                                           Theta_prev.ub)
            if values is not None:
                return values, None, 0 if results is None else len(results)
            last = results[-1]
            if last.status is Status.INFEASIBLE:
                return None, _falsified(len(results)), len(results)
            return None, _failed(len(results), last.status,
                                 f"the LP of row {len(results) - 1}"), len(results)
        results = solve_lps_joint(self.Theta0.H, both.H, both.h)
        last = results[-1]
        if last.status is Status.INFEASIBLE:
            return None, _falsified(len(results)), len(results)
        if last.status is not Status.OPTIMAL:
            return None, _failed(len(results), last.status,
                                 f"the LP of row {len(results) - 1}"), len(results)
        return np.array([r.value for r in results]), None, len(results)

    def _previous_h(self, Theta_prev: Polytope) -> np.ndarray:
        """``h_{θ,k−1}`` in the row order of Θ₀ (Θ_{k−1} has the same rows)."""
        return Theta_prev.h

    def propose(self, Theta_prev: Polytope, data: Transition) -> Proposal:
        if _box_inside(Theta_prev, data.delta):
            return Proposal(Theta_prev, 0, reason="Θ_{k−1} ⊆ Δ_k (its vertices satisfy "
                            "every row): the transition excludes nothing, no LP")
        bounds, refusal, lps = self._support_bounds(Theta_prev, data)
        if refusal is not None:
            return refusal
        h = np.minimum(bounds + self.margin, self._previous_h(Theta_prev))
        return Proposal(self._make(h), lps=lps, reason="" if lps else _BY_VERTICES)

    def _make(self, h: np.ndarray) -> Polytope:
        return Polytope(self.Theta0.H, h, name=f"Theta_{self.k + 1}")


#: :func:`vertex_supports` enumerates vertices only up to this dimension and this many
#: candidate row subsets (else the LPs run)
VERTEX_MAX_DIM = 3
VERTEX_MAX_SUBSETS = 5000
#: a candidate vertex satisfies every row within this (relative to the row's size)
VERTEX_FEAS_TOL = 1e-10
#: row subsets (rows scaled to unit ∞-norm) with a smaller ``|det|`` are near-singular: a
#: feasible candidate from one is not trusted (its rounding is not bounded), the LPs decide
VERTEX_MIN_DET = 1e-8


_BY_VERTICES = "bounds from the vertices of Θ_{k−1} ∩ Δ_k (vertex_supports), no LP"


@lru_cache(maxsize=64)
def _subsets(m: int, q: int) -> np.ndarray:
    """All ``q``-subsets of ``range(m)`` as rows (cached: the row count repeats per step)."""
    return np.array(list(combinations(range(m), q)), dtype=np.intp).reshape(-1, q)


def vertex_supports(C: np.ndarray, H: np.ndarray, h: np.ndarray, duals: bool = False
                    ) -> np.ndarray | tuple[np.ndarray, np.ndarray] | None:
    """``max {C[r] θ : Hθ <= h}`` for every row of ``C`` from the vertices of the bounded
    polytope ``{Hθ <= h}`` (a linear function attains its maximum over a polytope at a
    vertex): every ``q``-subset of rows with a nonsingular matrix gives a candidate
    ``θ``, kept if it satisfies every row within :data:`VERTEX_FEAS_TOL`. For ``q <=``
    :data:`VERTEX_MAX_DIM` with few rows (the 2-parameter chain: ``2q + 2n`` rows, at most
    a few hundred 2 × 2 systems in one batched solve) this replaces the ``2q`` LPs of the
    box and hypercube updates by one small array computation, exactly (the LPs' answers
    within rounding; ``tests/test_rapsf_speed.py``). ``None`` — the caller runs the LPs —
    when the dimension or the number of subsets is larger, when no candidate is feasible
    (possibly an empty set: the LP decides whether the model is falsified), or when a
    feasible candidate comes from an ill-conditioned subset (near-parallel rows: its
    rounding is not bounded by the tolerance). ``duals=True`` also returns, per row of
    ``C``, multipliers ``y`` on the rows of ``H`` from the maximizing vertex's subset
    (``Hᵀy = C[r]``; negative entries where that subset is not an optimal basis), for
    :func:`verified_upper`."""
    m, q = H.shape
    if q > VERTEX_MAX_DIM or m < q or comb(m, q) > VERTEX_MAX_SUBSETS:
        return None
    scale = np.abs(H).max(axis=1)
    if np.any(scale == 0):                           # a row without θ: the LPs decide
        return None
    Hn, hn = H / scale[:, None], h / scale           # the same rows, unit ∞-norm
    idx = _subsets(m, q)
    M = Hn[idx]                                      # (S, q, q)
    det = np.abs(np.linalg.det(M))
    regular = det > 1e-13                            # exactly parallel rows: no vertex
    M, b, det = M[regular], hn[idx[regular]], det[regular]
    if not len(M):
        return None
    theta = np.linalg.solve(M, b[:, :, None])[:, :, 0]                     # (S', q)
    feasible = np.all(theta @ Hn.T - hn <= VERTEX_FEAS_TOL * (1.0 + np.abs(hn)), axis=1)
    if not np.any(feasible) or np.min(det[feasible]) < VERTEX_MIN_DET:
        return None
    values = theta[feasible] @ C.T                                          # (F, rows of C)
    best = values.max(axis=0)
    if not duals:
        return best
    subsets, Mf = idx[regular][feasible], M[feasible]
    Y = np.zeros((C.shape[0], m))
    for r, at in enumerate(values.argmax(axis=0)):  # Mᵀ y_S = C[r] on the unit-norm rows
        y_s = np.linalg.solve(Mf[at].T, C[r])
        Y[r, subsets[at]] = y_s / scale[subsets[at]]
    return best, Y


#: a bound from the vertices is used only if its weak-duality verification
#: (:func:`verified_upper`) is within this (relative) of it; else the LPs decide
VERIFY_GAP = 1e-9


def box_supports(C: np.ndarray, H: np.ndarray, h: np.ndarray, lb: np.ndarray,
                 ub: np.ndarray) -> tuple[np.ndarray | None, list | None]:
    """``max {C[r]θ : Hθ <= h}`` for every row of ``C``, each raised to its verified bound
    (:func:`verified_upper` over the box ``[lb, ub] ⊇ {Hθ <= h}``): from the vertices
    (:func:`vertex_supports`, no LP) when their multipliers verify the values within
    :data:`VERIFY_GAP`, else from the joint LPs and their duals. Returns ``(values,
    results)``: ``results`` the LP results (``None`` when no LP ran); ``values`` is ``None``
    when an LP did not end optimal (its status is in ``results[-1]``)."""
    got = vertex_supports(C, H, h, duals=True)
    if got is not None:
        values, Y = got
        ver = np.array([verified_upper(c, H, h, lb, ub, y) for c, y in zip(C, Y, strict=True)])
        if np.all(ver - values <= VERIFY_GAP * (1.0 + np.abs(values))):
            return np.maximum(values, ver), None
    results = solve_lps_joint(C, H, h)
    if results[-1].status is not Status.OPTIMAL:
        return None, results
    values = np.array([r.value for r in results])
    ver = np.array([verified_upper(c, H, h, lb, ub, r.dual) if r.dual is not None else v
                    for c, r, v in zip(C, results, values, strict=True)])
    return np.maximum(values, ver), results


def _box_inside(Theta: Polytope, delta: object) -> bool:
    """Whether a box ``Θ_{k−1}`` lies in ``Δ_k = {Hθ <= h}`` (all ``2^q`` vertices satisfy
    every row). Then ``max {H_θ[r] θ : Θ_{k−1} ∩ Δ_k} = max {H_θ[r] θ : Θ_{k−1}}``: the
    fixed-shape update of a box returns ``Θ_{k−1}`` itself (the support LPs would give its
    bounds, which the clipping to ``h_{θ,k−1}`` returns exactly). Sound even when the test
    is rounded: ``Θ_{k−1}`` always contains ``Θ_{k−1} ∩ Δ_k``. Only for boxes (vertices
    without enumeration); on the §4.7 chain most steps are such uninformative ones."""
    if not isinstance(Theta, Box) or delta.H.shape[0] == 0:
        return isinstance(Theta, Box)
    # max over the box of each row, attained at a vertex: Σ_j max(H_rj ub_j, H_rj lb_j)
    # (the vertex test without enumerating the 2^q vertices)
    top = np.maximum(delta.H * Theta.ub, delta.H * Theta.lb).sum(axis=1)
    return bool(np.all(top <= delta.h))


class BoxUpdate(FixedShapeUpdate):
    """The fixed-shape update with an axis-aligned box: ``2q`` LPs per step (SPEC §2.19
    [Default] for the §4.7 example); Θ_k is a :class:`~balustrade.dsl.sets.Box`."""

    def __init__(self, system: ParametricLinearSystem, W: Polytope, Theta0: Box,
                 margin: float = MARGIN, name: str = "box_update"):
        super().__init__(system, W, require_box(Theta0, name), margin=margin, name=name)

    def _previous_h(self, Theta_prev: Polytope) -> np.ndarray:
        box = require_box(Theta_prev, self.name)
        return np.concatenate([box.ub, -box.lb])

    def _make(self, h: np.ndarray) -> Box:
        q = self.system.q
        ub, lb = h[:q], -h[q:]
        lb = np.minimum(lb, ub)  # LP rounding on a flat set
        return Box(lb, ub, name=f"Theta_{self.k + 1}")


def hypercube_centre(lo: np.ndarray, hi: np.ndarray, centre_prev: np.ndarray,
                     eta_prev: float, rule: str = "nested") -> tuple[np.ndarray, float]:
    """Centre and half-width ``(θ̄_k, η_k)`` of the hypercube update of SPEC §2.19 from the
    bounding box ``[lo, hi]`` of ``Θ_{k−1} ∩ Δ_k`` and ``Θ_{k−1} = B_∞(θ̄_{k−1}, η_{k−1})``.

    ``η_k = max_j (hi_j − lo_j)/2``; ``rule="nested"`` picks, per coordinate, the point of
    ``[hi_j − η_k, lo_j + η_k] ∩ [θ̄_{k−1,j} − η_{k−1} + η_k, θ̄_{k−1,j} + η_{k−1} − η_k]``
    (non-empty when ``[lo, hi] ⊆ Θ_{k−1}``) nearest the box's midpoint: the cube contains
    ``[lo, hi]`` and lies in Θ_{k−1}. ``rule="naive"`` takes the midpoint itself, which
    contains ``[lo, hi]`` but can leave Θ_{k−1}."""
    mid = 0.5 * (lo + hi)
    eta = float(np.max(hi - lo)) / 2.0
    if rule == "naive":
        return mid, eta
    if rule != "nested":
        raise BalustradeError(f"hypercube_centre: rule must be 'nested' or 'naive', got "
                              f"{rule!r}")
    eta = min(eta, float(eta_prev))
    a = np.maximum(hi - eta, centre_prev - eta_prev + eta)
    b = np.minimum(lo + eta, centre_prev + eta_prev - eta)
    b = np.maximum(a, b)  # rounding only: the interval is non-empty in exact arithmetic
    return np.clip(mid, a, b), eta


class HypercubeUpdate(SetEstimator):
    """``Θ_k = B_∞(θ̄_k, η_k)``: bounding box of ``Θ_{k−1} ∩ Δ_k`` (``2q`` LPs), then the
    centre of :func:`hypercube_centre`. Θ₀ must be a cube."""

    def __init__(self, system: ParametricLinearSystem, W: Polytope, Theta0: Box,
                 centre: str = "nested", margin: float = MARGIN,
                 name: str = "hypercube_update"):
        box = require_box(Theta0, name)
        widths = box.ub - box.lb
        if not np.allclose(widths, widths[0], rtol=1e-12, atol=0.0):
            raise BalustradeError(f"{name}: Theta0 must be a hypercube (equal widths) for the "
                                  f"hypercube update, got widths {widths.tolist()}")
        if centre not in ("nested", "naive"):
            raise BalustradeError(f"{name}: centre must be 'nested' or 'naive', got "
                                  f"{centre!r}")
        super().__init__(system, W, box, name=name)
        self.centre = centre
        self.margin = as_scalar(margin, f"{name}: margin", low=0.0)

    def propose(self, Theta_prev: Polytope, data: Transition) -> Proposal:
        prev = require_box(Theta_prev, self.name)
        both = data.delta.intersect(prev)
        q = self.system.q
        C = np.vstack([np.eye(q), -np.eye(q)])
        values, results = box_supports(C, both.H, both.h, prev.lb, prev.ub)
        lps = 0 if results is None else len(results)
        if values is None:
            last = results[-1]
            if last.status is Status.INFEASIBLE:
                return _falsified(lps)
            return _failed(lps, last.status, "a bound LP")
        hi, lo = values[:q], -values[q:]
        lo = np.maximum(lo - self.margin, prev.lb)
        hi = np.minimum(hi + self.margin, prev.ub)
        centre_prev = 0.5 * (prev.lb + prev.ub)
        eta_prev = float(np.max(prev.ub - prev.lb)) / 2.0
        c, eta = hypercube_centre(lo, hi, centre_prev, eta_prev, rule=self.centre)
        return Proposal(Box(c - eta, c + eta, name=f"Theta_{self.k + 1}"), lps,
                        reason="" if lps else _BY_VERTICES)


__all__ = ["BoxUpdate", "ExactUpdate", "FixedShapeUpdate", "HypercubeUpdate",
           "hypercube_centre", "remove_redundant", "vertex_supports"]
