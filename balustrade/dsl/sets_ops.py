"""Binary set operations behind :meth:`Set.minkowski_sum` and :meth:`Set.is_subset_of`
(SPEC §1.5, §1.11)."""

from __future__ import annotations

import numpy as np

from balustrade.dsl import sets_geometry as geo
from balustrade.dsl.sets import Box, Ellipsoid, Polytope
from balustrade.dsl.sets_base import Set
from balustrade.dsl.sets_function import FunctionSet
from balustrade.errors import BalustradeError


def minkowski_sum(a: Set, b: Set, name: str | None) -> Set:
    """``a ⊕ b`` (SPEC §1.5, §1.11 ``E_i = ⊕_j (A+BK)^j W``).

    * Box ⊕ Box → Box (exact).
    * Polytope ⊕ Polytope → Polytope, hull of the pairwise vertex sums (exact; bounded,
      dimension <= 6).
    * Ellipsoid ⊕ Ellipsoid → the outer ellipsoid with shape matrix
      ``(1 + 1/p) Q_a + (1 + p) Q_b``, ``Q = P⁻¹``, at the trace-minimising
      ``p = sqrt(tr Q_a / tr Q_b)`` (an over-approximation; its support exceeds
      ``h_a + h_b`` except along special directions).
    * Polytope ⊕ Ellipsoid (either order) → the outer polytope with the same normals,
      ``{Hx <= h + [h_E(H_jᵀ)]_j}`` (an over-approximation; exact support along each
      non-redundant row). A Box stays a Box.
    """
    a._check_same_dim(b, "⊕")
    new_name = name or f"{a.name}⊕{b.name}"
    if isinstance(a, FunctionSet) or isinstance(b, FunctionSet):
        raise BalustradeError(f"{new_name}: Minkowski sums of a FunctionSet have no "
                              "representation")
    if isinstance(a, Box) and isinstance(b, Box):
        return Box(a.lb + b.lb, a.ub + b.ub, name=new_name)
    if isinstance(a, Ellipsoid) and isinstance(b, Ellipsoid):
        Qa, Qb = a.shape_matrix, b.shape_matrix
        p = float(np.sqrt(np.trace(Qa) / np.trace(Qb)))
        Q = (1.0 + 1.0 / p) * Qa + (1.0 + p) * Qb
        Pn = np.linalg.inv(0.5 * (Q + Q.T))
        return Ellipsoid(0.5 * (Pn + Pn.T), a.center + b.center, name=new_name)
    if isinstance(a, Ellipsoid):
        a, b = b, a
    if isinstance(b, Ellipsoid):
        assert isinstance(a, Polytope)
        if isinstance(a, Box):
            r = np.sqrt(np.diag(b.shape_matrix))
            return Box(a.lb + b.center - r, a.ub + b.center + r, name=new_name)
        s = np.array([b.support(row) for row in a.H])
        return Polytope(a.H, a.h + s, name=new_name)
    assert isinstance(a, Polytope) and isinstance(b, Polytope)
    for p_ in (a, b):
        p_._require_bounded(f"minkowski_sum({new_name})")
    Va, Vb = a.vertices(), b.vertices()
    V = (Va[:, None, :] + Vb[None, :, :]).reshape(-1, a.dim)
    Hs, hs = geo.hull_halfspaces(V, new_name)
    return Polytope(Hs, hs, name=new_name)


def is_subset(s: Set, t: Set, tol: float) -> bool:
    """``s ⊆ t`` up to ``tol`` in units of ``t.c``.

    * ``t`` a Polytope/Box: ``h_s(H_jᵀ) <= h_j + tol`` for every row (exact for every ``s``
      with an exact support function; a FunctionSet's NLP support is exact when convex).
    * ``t`` an Ellipsoid: ``s`` an Ellipsoid → ``max_{x∈s} c_t(x) <= tol`` by the
      trust-region subproblem; ``s`` a bounded Polytope → the same maximum over its vertices
      (``c_t`` is convex).
    """
    s._check_same_dim(t, "⊆")
    if isinstance(t, Polytope):
        if isinstance(s, Box) and isinstance(t, Box):
            return bool(np.all(s.ub <= t.ub + tol) and np.all(t.lb <= s.lb + tol))
        return all(s.support(row) <= hj + tol for row, hj in zip(t.H, t.h, strict=True))
    if isinstance(t, Ellipsoid):
        if isinstance(s, Ellipsoid):
            return bool(t.max_quadratic_over(s) - 1.0 <= tol)
        if isinstance(s, Polytope):
            if not s.is_bounded():
                return False
            return bool(np.all(t.contains_many(s.vertices(), tol=tol)))
    raise BalustradeError(f"{s.name} ⊆ {t.name}: containment of a {type(s).__name__} in a "
                          f"{type(t).__name__} is not decidable here")


