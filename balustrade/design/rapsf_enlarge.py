"""The enlarged terminal set of the homothetic-tube RAPSF offline: build it from recorded
solutions and check Assumption 4.11 for it (thesis Theorem 4.12, Remark 4.13, SPEC §2.22).

* :func:`enlarged_terminal_set` — ``co({(z*_i, α*_i)} ∪ {(z*_i + α*_i x^j, 0)} ∪ 𝕏_f)`` from a
  list of solved tubes ``(z, α)`` (e.g. all solves of a closed-loop run: the thesis builds
  ``𝓕_f(Θ₁₅₀)`` "using all available data after the simulation"), pruned to its extreme
  points by LPs;
* :func:`prune_terminal_set` — drop generators inside the hull of the others (one LP each);
* :func:`check_enlarged_terminal` — Assumption 4.11 at every generator of a hull terminal set
  (base vertices included): one LP per generator finds ``v`` and a successor pair in the hull
  with (4.5c), (4.5d). The feasible ``(z, α, v, z⁺, α⁺, λ)`` form a polyhedron, so checking the
  generators suffices (a convex combination of their certificates is one for any point).

The online counterpart (generators added after every solve of Algorithm 4.1) is
:class:`balustrade.control.rapsf_enlarge.TerminalEnlargement`, used by ``RAPSF(enlarge=True)``.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import scipy.optimize

from balustrade._checks import as_matrix
from balustrade.backends.hull import extreme_points, hull_distances
from balustrade.design.rapsf import CheckReport, joint_set
from balustrade.dsl.joint import JointPolytope
from balustrade.errors import BalustradeError, ShapeError
from balustrade.problems.rapsf import (
    TerminalSet,
    check_parametric_system,
    model_matrices,
    tube_constants,
)
from balustrade.problems.rapsf_enlarge import base_generators, tube_pairs, zero_dilation_points


def enlarged_terminal_set(n: int, tubes: Iterable[tuple[np.ndarray, np.ndarray]],
                          base: TerminalSet | None = None,
                          X0_vertices: np.ndarray | None = None, prune: bool = True,
                          tol: float = 1e-7) -> TerminalSet:
    """The hull (4.10) of the pairs of the solved tubes ``(z, α)`` (``z`` ``n × N+1``) over
    ``base`` (``None``: the §4.7 default), with the zero-dilation points of Remark 4.13 when
    ``X0_vertices`` (rows) is given. Valid for a parameter set ``Θ`` only if every tube was
    solved for a set containing ``Θ`` (Assumption 4.2 makes that true for the last one)."""
    cols = []
    for z, a in tubes:
        cols.append(tube_pairs(z, a, n))
        if X0_vertices is not None:
            cols.append(zero_dilation_points(z, a, X0_vertices))
    V = np.hstack(cols) if cols else np.zeros((n + 1, 0))
    ts = TerminalSet.from_generators(V[:n], V[n], base)
    return prune_terminal_set(ts, tol) if prune and V.shape[1] else ts


def prune_terminal_set(terminal: TerminalSet, tol: float = 1e-7) -> TerminalSet:
    """The same hull with the generators that lie in the hull of the others (and of the base
    set) removed: first all against the base set (one warm LP model), then one by one."""
    V = terminal.generators
    if V.shape[1] == 0:
        return terminal
    n = V.shape[0] - 1
    fixed = base_generators(terminal, n)
    if fixed is not None:
        d = hull_distances(V, fixed)
        V = V[:, d > tol * (1.0 + np.abs(V).sum(axis=0))]
    V = V[:, extreme_points(V, tol, fixed=fixed)] if V.shape[1] else V
    return TerminalSet.from_generators(V[:n], V[n], _base_of(terminal))


def _base_of(terminal: TerminalSet) -> TerminalSet | None:
    return None if terminal.H_T is None else TerminalSet(terminal.H_T, terminal.h_T)


def check_enlarged_terminal(system: object, X0: object, W: object, K: np.ndarray,
                            vertices: np.ndarray, F: np.ndarray | JointPolytope,
                            G: np.ndarray | None, terminal: TerminalSet,
                            tol: float = 1e-7) -> CheckReport:
    """Assumption 4.11 for the hull terminal set ``terminal`` and the vertices ``θ^j`` of
    ``Θ`` (rows of ``vertices``): at every generator ``(z, α)`` (and every vertex of the
    base set) an LP minimizes the uniform violation ``ε`` of (4.5c), (4.5d) over ``v`` and
    ``(z⁺, α⁺) = Σλ_g(Z_g, a_g) + (z', α')`` in the hull (perspective form). ``ok`` when the
    largest ``ε`` is ``<= tol``; ``details["violations"]`` has one ``ε`` per generator (the
    recorded ones first, then the base vertices). ``𝒵``: a
    :class:`~balustrade.dsl.joint.JointPolytope` ``F`` (``G=None``) or the matrices
    ``F, G``."""
    n, m, _ = check_parametric_system(system, "check_enlarged_terminal")
    K = as_matrix(K, "check_enlarged_terminal: K", (m, n))
    Z = joint_set(F, G, n, m, "check_enlarged_terminal")
    if not isinstance(terminal, TerminalSet) or terminal.Z is None:
        raise BalustradeError("check_enlarged_terminal: terminal must be a TerminalSet with "
                              "numeric generators (TerminalSet.from_generators)")
    V = terminal.generators
    if V.shape[0] != n + 1:
        raise ShapeError("check_enlarged_terminal: terminal generators Z", f"{n} rows",
                         (V.shape[0] - 1, V.shape[1]))
    c = tube_constants(X0, W, system, K, np.atleast_2d(vertices), Z, None)
    base = base_generators(terminal, n)
    if base is None:
        raise BalustradeError("check_enlarged_terminal: the vertices of the base terminal set "
                              "could not be enumerated (dimension n + 1 > 6 or unbounded)")
    at = np.hstack([V, base])
    eps = np.array([_successor_lp(system, c, K, np.atleast_2d(vertices), Z, terminal,
                                  at[:n, g], float(at[n, g]), n, m) for g in
                    range(at.shape[1])])
    worst = float(eps.max())
    return CheckReport(worst <= tol, worst, {"violations": eps, "generators": at})


def _successor_lp(system: object, c: object, K: np.ndarray, vertices: np.ndarray,
                  Z: JointPolytope, terminal: TerminalSet, z: np.ndarray,
                  a: float, n: int, m: int) -> float:
    """``min ε`` over ``[v, λ, λ_f, z', α', ε]`` (``z'`` only for an H-representation base)
    s.t. (4.5c) at every vertex and (4.5d) relaxed by ``ε``, ``(z⁺, α⁺)`` in the hull."""
    Vg = terminal.generators
    nG = Vg.shape[1]
    Zg, ag = Vg[:n], Vg[n]
    HX = c.HX
    nX = HX.shape[0]
    has_zb = terminal.H_T is not None
    nz = n if has_zb else 0
    # column blocks: v (m) | λ (nG) | λ_f (1) | z' (nz) | α' (1) | ε (1)
    nv = m + nG + 1 + nz + 2
    iv, il, ilf, izb, iab, ie = 0, m, m + nG, m + nG + 1, m + nG + 1 + nz, nv - 1
    rows, rhs = [], []
    for j, th in enumerate(vertices):
        A, B = model_matrices(system, th)
        Acl = A + B @ K
        R = np.zeros((nX, nv))
        R[:, iv:il] = HX @ B
        R[:, il:ilf] = -(HX @ Zg) - np.outer(np.ones(nX), ag)     # −H_X z⁺ − α⁺ (hull part)
        if has_zb:
            R[:, izb:iab] = -HX
        R[:, iab] = -1.0
        R[:, ie] = -1.0
        rows.append(R)
        rhs.append(-(HX @ Acl @ z + a * c.s[:, j] + c.w_bar))
    R = np.zeros((Z.G.shape[0], nv))
    R[:, iv:il] = Z.G
    R[:, ie] = -1.0
    rows.append(R)
    rhs.append(1.0 - Z.closed_loop(K) @ z - a * c.t)
    if has_zb:                                   # H_T z' + h_T α' <= λ_f
        H_T = np.asarray(terminal.H_T, float)
        R = np.zeros((H_T.shape[0], nv))
        R[:, izb:iab] = H_T
        R[:, iab] = np.asarray(terminal.h_T, float).ravel()
        R[:, ilf] = -1.0
    else:                                        # α' <= λ_f
        R = np.zeros((1, nv))
        R[0, iab], R[0, ilf] = 1.0, -1.0
    rows.append(R)
    rhs.append(np.zeros(R.shape[0]))
    Aeq = np.zeros((1, nv))
    Aeq[0, il:izb] = 1.0                         # Σλ + λ_f = 1
    cost = np.zeros(nv)
    cost[ie] = 1.0
    bounds = ([(None, None)] * m + [(0, None)] * (nG + 1) + [(None, None)] * nz
              + [(0, None), (None, None)])
    res = scipy.optimize.linprog(cost, A_ub=np.vstack(rows), b_ub=np.concatenate(rhs),
                                 A_eq=Aeq, b_eq=[1.0], bounds=bounds)
    if res.status != 0:
        raise BalustradeError(f"check_enlarged_terminal: LP at generator {(z, a)} failed "
                              f"({res.message})")
    return float(res.fun)


__all__ = ["check_enlarged_terminal", "enlarged_terminal_set", "prune_terminal_set"]
