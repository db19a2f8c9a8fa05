"""Joint state–input constraints ``𝒵 = {(x, u) : F x + G u <= 1}`` (thesis Chapter 4, SPEC
§2.20: the constraint set of (4.5d)) as a set and as a horizon block.

:class:`JointPolytope` is the set: a :class:`~balustrade.dsl.sets.Polytope` in ``(x, u)``
(``H = [F G]``, ``h = 1``, so every support function, sample and inclusion test of a
polytope applies) that also knows its two blocks ``F`` (``p × n``) and ``G`` (``p × m``).
``JointPolytope.product(X, U)`` is ``X × U`` with every row divided by its bound. The
supports a tube needs are methods:

* :meth:`JointPolytope.closed_loop` ``F + G K``: the rows on ``x`` under ``u = K x + v``;
* :meth:`JointPolytope.feedback_support` ``t_r = max_{e∈S} [F + G K]_r e`` (SPEC §2.20's
  ``t_r`` for ``S = 𝕏₀``; the tightening of a rigid tube ``x ∈ z ⊕ S`` for an error set
  ``S``).

:func:`joint_constraint` (also :meth:`OCP.joint_constraint <balustrade.dsl.ocp.OCP>`) is the
block. For the columns ``i`` of ``x`` and ``u`` (default: the problem's own trajectories,
steps ``0 … N−1``) it imposes, row by row,

* plain:       ``F x_i + G u_i <= 1 − Δ_i``;
* ``feedback=K`` (tube law ``κ(x, v) = K x + v``, ``u`` holds ``v``):
  ``(F + G K) x_i + G v_i <= 1 − Δ_i``;
* ``tube=S`` (rigid tube ``x ∈ z_i ⊕ S``, ``x`` holds ``z``): ``… + t <= 1 − Δ_i``;
* ``tube=(alpha, S)`` (homothetic tube ``z_i ⊕ α_i S``, (4.5d) of SPEC §2.20 with ``S = 𝕏₀``):
  ``(F + G K) z_i + α_i t + G v_i <= 1 − Δ_i`` — exact for ``α_i >= 0`` because the rows
  are affine in the tube point.

Every row is affine in the decision variables (``t`` and ``Δ_i`` are numbers), so the block
lowers on every backend (CasADi, cvxpy, the direct conic/QP backend).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from balustrade._checks import as_float_array, as_matrix, as_vector, check_name
from balustrade.dsl.sets import Polytope, Set
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError

if TYPE_CHECKING:  # no import cycle: ocp.py imports this module lazily
    from balustrade.dsl.ocp import OCP, Block, Tightening


class JointPolytope(Polytope):
    """``𝒵 = {(x, u) : F x + G u <= 1}`` (SPEC §2.20), a polytope in the stacked ``(x, u)``.

    ``F`` is ``p × n``, ``G`` is ``p × m`` (same number of rows ``p >= 1``), both finite.
    With ``h`` (``p`` positive finite bounds) the set ``{F x + G u <= h}`` is stored with
    every row divided by its bound. The origin is always inside (the right-hand side is
    positive), so the set is never empty. Wrong shapes → :class:`ShapeError` naming ``F``,
    ``G`` or ``h``; NaN or inf → :class:`NonFiniteError`."""

    def __init__(self, F: object, G: object, h: object | None = None, name: str = "Z"):
        check_name(name, "JointPolytope: name")
        F = as_matrix(F, f"{name}: F")
        if F.shape[0] == 0 or F.shape[1] == 0:
            raise ShapeError(f"{name}: F", "at least one row and one column (p × n, the "
                             "state dimension n)", F.shape)
        G = as_matrix(G, f"{name}: G (one row per row of F, shape (p, m))",
                      (F.shape[0], None))
        if G.shape[1] == 0:
            raise ShapeError(f"{name}: G", "at least one column (p × m, the input "
                             "dimension m)", G.shape)
        if h is not None:
            h_arr = as_float_array(h, f"{name}: h (one bound per row of F and G)")
            if h_arr.ndim > 2 or h_arr.size != F.shape[0]:
                raise ShapeError(f"{name}: h (one bound per row of F and G)",
                                 (F.shape[0],), h_arr.shape)
            h_arr = h_arr.reshape(-1)
            if not np.all(np.isfinite(h_arr)):
                raise NonFiniteError(f"{name}: h contains NaN or inf: {h_arr}")
            if np.any(h_arr <= 0):
                raise BalustradeError(f"{name}: h must be positive (the origin inside 𝒵, "
                                      f"so that the rows can be written F x + G u <= 1); "
                                      f"rows {np.flatnonzero(h_arr <= 0).tolist()} are "
                                      f"{h_arr[h_arr <= 0].tolist()}")
            F, G = F / h_arr[:, None], G / h_arr[:, None]
        object.__setattr__(self, "F", F)
        object.__setattr__(self, "G", G)
        super().__init__(np.hstack([F, G]), np.ones(F.shape[0]), name=name)

    def __repr__(self) -> str:
        F = getattr(self, "F", None)
        if F is None:  # during construction
            return f"JointPolytope(<incomplete>, name={getattr(self, 'name', None)!r})"
        return (f"JointPolytope(rows={F.shape[0]}, nx={self.nx}, nu={self.nu}, "
                f"name={self.name!r})")

    @classmethod
    def product(cls, X: Polytope, U: Polytope, name: str = "Z") -> JointPolytope:
        """``X × U`` as ``{F x + G u <= 1}``: the rows of ``X`` (``F = H_X / h_X``, ``G = 0``)
        then those of ``U``; both must contain the origin in their interior (positive row
        bounds), else :class:`BalustradeError` naming the set and its bounds."""
        for label, S in (("X", X), ("U", U)):
            if not isinstance(S, Polytope):
                raise BalustradeError(f"JointPolytope.product: {label} must be a Polytope "
                                      f"(or Box), got {type(S).__name__}")
            if not np.all(np.isfinite(S.h)) or np.any(S.h <= 0):
                raise BalustradeError(f"JointPolytope.product: {label} ({S.name}) must "
                                      f"contain the origin in its interior (finite positive "
                                      f"row bounds, got {S.h.tolist()})")
        F = np.vstack([X.H / X.h[:, None], np.zeros((U.H.shape[0], X.dim))])
        G = np.vstack([np.zeros((X.H.shape[0], U.dim)), U.H / U.h[:, None]])
        return cls(F, G, name=name)

    # -- dimensions -------------------------------------------------------------------------
    @property
    def nx(self) -> int:
        """The state dimension ``n`` (columns of ``F``)."""
        return int(self.F.shape[1])

    @property
    def nu(self) -> int:
        """The input dimension ``m`` (columns of ``G``)."""
        return int(self.G.shape[1])

    @property
    def n_rows(self) -> int:  # type: ignore[override]
        return int(self.F.shape[0])

    def is_empty(self) -> bool:
        """Never: ``(0, 0)`` satisfies ``F·0 + G·0 = 0 <= 1`` (no LP)."""
        return False

    def check_dims(self, nx: int, nu: int, where: str) -> JointPolytope:
        """``self`` if its blocks fit a system with ``nx`` states and ``nu`` inputs, else a
        :class:`ShapeError` naming ``F``/``G`` and both shapes."""
        if self.nx != nx:
            raise ShapeError(f"{where}: {self.name}.F", f"{nx} columns (the state dimension)",
                             self.F.shape)
        if self.nu != nu:
            raise ShapeError(f"{where}: {self.name}.G", f"{nu} columns (the input dimension)",
                             self.G.shape)
        return self

    # -- rows and supports ----------------------------------------------------------------------
    def c_pair(self, x: ca.SX, u: ca.SX) -> ca.SX:
        """``F x + G u − 1`` for columns ``x`` (``n × 1``) and ``u`` (``m × 1``): the pair is
        in ``𝒵`` iff every row is ``<= 0``."""
        self._check_point_dim(ca.vertcat(x, u), "c_pair(x, u)")
        return ca.mtimes(ca.DM(self.F), x) + ca.mtimes(ca.DM(self.G), u) - 1

    def contains_pair(self, x: object, u: object, tol: float = 1e-9) -> bool:
        """Whether the numeric pair ``(x, u)`` lies in ``𝒵`` (up to ``tol``)."""
        x = as_vector(x, f"{self.name}.contains_pair(x)", self.nx)
        u = as_vector(u, f"{self.name}.contains_pair(u)", self.nu)
        return self.contains(np.concatenate([x, u]), tol)

    def closed_loop(self, K: object) -> np.ndarray:
        """``F + G K`` (``p × n``): the rows of ``𝒵`` on ``x`` under ``u = K x + v``."""
        K = as_matrix(K, f"{self.name}.closed_loop: K", (self.nu, self.nx))
        return self.F + self.G @ K

    def feedback_support(self, K: object | None, S: Set,
                         vertices: np.ndarray | None = None) -> np.ndarray:
        """``t_r = max_{e∈S} [F + G K]_r e`` for every row (SPEC §2.20; ``K = None`` means
        ``F``): one support evaluation per row (closed form for a box or an ellipsoid, an LP
        for a polytope), or ``max_v [F + G K]_r e^v`` over given ``vertices`` of ``S``
        (rows; same values, one matrix product)."""
        D = self.F if K is None else self.closed_loop(K)
        if isinstance(S, Set) and S.dim != self.nx:
            raise ShapeError(f"{self.name}.feedback_support: S ({S.name})",
                             f"dimension {self.nx} (the state dimension)", f"dimension {S.dim}")
        return row_supports(D, S, vertices, f"{self.name}.feedback_support")


def row_supports(D: object, S: Set, vertices: np.ndarray | None = None,
                 where: str = "row_supports") -> np.ndarray:
    """``max_{e∈S} d_r e`` for every row ``d_r`` of ``D`` (``t`` of SPEC §2.20 for
    ``D = F + G K``, ``s`` for ``D = H_X A_cl(θ^j)``): one support evaluation per row
    (closed form for a box or an ellipsoid, an LP for a polytope), or ``max_v d_r e^v`` over
    given ``vertices`` of ``S`` (rows; same values, one matrix product). ``S`` unbounded
    along a row → :class:`BalustradeError` (no finite tightening exists)."""
    if not isinstance(S, Set):
        raise BalustradeError(f"{where}: S must be a balustrade Set, got {type(S).__name__}")
    D = as_matrix(D, f"{where}: rows", (None, S.dim))
    if vertices is not None:
        V = as_matrix(vertices, f"{where}: vertices", (None, S.dim))
        return np.max(D @ V.T, axis=1)
    t = np.array([S.support(row) for row in D])
    if not np.all(np.isfinite(t)):
        raise BalustradeError(f"{where}: {S.name} is unbounded along rows "
                              f"{np.flatnonzero(~np.isfinite(t)).tolist()}: no tightening "
                              "keeps the constraints")
    return t


def as_joint(Z: object, G: object | None, where: str) -> JointPolytope:
    """``Z`` itself when it is a :class:`JointPolytope` (then ``G`` must be ``None``), else
    ``JointPolytope(Z, G)`` from the two matrices ``F = Z`` and ``G`` (the older spelling
    ``(F, G)`` of the Chapter 4 functions)."""
    if isinstance(Z, JointPolytope):
        if G is not None:
            raise BalustradeError(f"{where}: pass either the JointPolytope 𝒵 (with G=None) "
                                  "or the matrices F and G, not both")
        return Z
    if G is None:
        raise BalustradeError(f"{where}: G is missing: pass a JointPolytope 𝒵, or the "
                              f"matrices F and G of F x + G u <= 1 (got F of type "
                              f"{type(Z).__name__} and G=None)")
    return JointPolytope(Z, G, name=f"{where}: Z")


def _tube(tube: object, cols: int, where: str) -> tuple[ca.SX | None, Set | None]:
    """``(alpha, S)`` of a ``tube`` argument: ``None``, a set ``S`` (``alpha = 1``) or a pair
    ``(alpha, S)`` with ``alpha`` a ``1 × cols`` expression (one dilation per column)."""
    if tube is None:
        return None, None
    if isinstance(tube, Set):
        return None, tube
    if not (isinstance(tube, tuple) and len(tube) == 2 and isinstance(tube[1], Set)):
        raise BalustradeError(f"{where}: tube must be None, a Set S (x ∈ z ⊕ S) or a pair "
                              f"(alpha, S) (x ∈ z_i ⊕ alpha_i S), got {type(tube).__name__}")
    alpha = tube[0]
    if not isinstance(alpha, (ca.SX, ca.DM)):
        alpha = ca.DM(as_float_array(alpha, f"{where}: tube dilations alpha"))
    alpha = ca.SX(alpha)
    if alpha.numel() < cols or 1 not in alpha.shape:
        raise ShapeError(f"{where}: tube dilations alpha", f"a row of at least {cols} entries "
                         "(one per step)", alpha.shape)
    alpha = ca.vec(alpha).T
    const = [(i, float(alpha[i])) for i in range(alpha.numel()) if alpha[i].is_constant()]
    bad = [(i, a) for i, a in const if not np.isfinite(a) or a < 0]
    if bad:  # the rows α_i t are exact for α_i >= 0 only (module docstring)
        raise BalustradeError(f"{where}: tube dilations alpha (shape {alpha.shape}) must be "
                              f"finite and >= 0 (z_i ⊕ α_i S; the rows are exact only for "
                              f"α_i >= 0), got {bad[0][1]} at step {bad[0][0]}")
    return alpha, tube[1]


def joint_constraint(ocp: OCP, Z: JointPolytope, x: ca.SX | None = None,
                     u: ca.SX | None = None, steps: list[int] | None = None,
                     feedback: object | None = None, tube: object = None,
                     tube_vertices: np.ndarray | None = None, tightening: Tightening = None,
                     name: str = "joint", tag: str = "state") -> Block:
    """``(x_i, u_i) ∈ 𝒵`` (SPEC §2.20) for the ``steps`` (default: every column of ``u``),
    with the tube forms of the module docstring: ``feedback=K`` (``u`` holds ``v`` of
    ``K x + v``), ``tube=S`` or ``tube=(alpha, S)`` (``x`` holds the tube centres ``z``;
    ``tube_vertices``, the vertices of ``S`` as rows, replace the support LPs by one
    matrix product), ``tightening`` ``Δ_i`` (a number, one per step, or ``i ↦ Δ_i``).
    ``x``/``u`` default to the problem's state and input trajectories. Returns the block
    (one row per row of ``𝒵`` and step, column-major)."""
    where = f"{ocp.name}: {name}"
    if not isinstance(Z, JointPolytope):
        raise BalustradeError(f"{where}: expected a JointPolytope 𝒵 (build one with "
                              f"JointPolytope(F, G) or JointPolytope.product(X, U)), got "
                              f"{type(Z).__name__}")
    if x is None or u is None:
        sys = ocp._need_system(f"{name} without x and u")
        x = ocp.x if x is None else x
        u = ocp.u if u is None else u
        Z.check_dims(sys.nx, sys.nu, where)
    x, u = _symbolic(x, f"{where}: x"), _symbolic(u, f"{where}: u")
    Z.check_dims(x.shape[0], u.shape[0], where)
    if steps is None:
        steps = list(range(u.shape[1]))
    else:
        steps = ocp._steps(steps, name)
    bad = [i for i in steps if i >= min(x.shape[1], u.shape[1])]
    if bad:
        raise BalustradeError(f"{where}: steps {bad} outside the columns of x "
                              f"({x.shape[1]}) and u ({u.shape[1]})")
    delta = ocp._deltas(tightening, steps, name)
    alpha, S = _tube(tube, max(steps) + 1, where)
    D = Z.F if feedback is None else Z.closed_loop(feedback)
    t = None if S is None else Z.feedback_support(feedback, S, tube_vertices)
    Dd, Gd = ca.DM(D), ca.DM(Z.G)
    rows = []
    for i, d in zip(steps, delta, strict=True):
        row = ca.mtimes(Dd, x[:, i])
        if t is not None:
            row = row + (ca.DM(t) if alpha is None else alpha[i] * ca.DM(t))
        row = row + ca.mtimes(Gd, u[:, i])
        rows.append(row + d if d else row)
    return ocp.le(ca.horzcat(*rows), 1.0, name=name, tag=tag, set=Z.name)


def _symbolic(value: object, where: str) -> ca.SX:
    if isinstance(value, (ca.SX, ca.DM)):
        return ca.SX(value)
    raise BalustradeError(f"{where}: expected a CasADi SX matrix (a variable of the OCP, "
                          f"one column per step), got {type(value).__name__}")


__all__ = ["JointPolytope", "as_joint", "joint_constraint", "row_supports"]
