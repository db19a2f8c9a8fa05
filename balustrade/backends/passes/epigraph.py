"""The epigraph pass: non-smooth cost terms become epigraph variables and rows.

``Epigraph().apply(ocp)`` rewrites an :class:`~balustrade.dsl.ocp.OCP` into a
:class:`SmoothProblem` — ``min f(w, p)`` over ``lbx <= w <= ubx``, ``lbg <= g(w, p) <= ubg``
with ``f`` and ``g`` smooth — whose decision vector is the OCP's
:attr:`~balustrade.dsl.ocp.OCP.variable_layout` :meth:`extended
<balustrade.dsl.layout.Layout.extend>` by one epigraph block ``t`` per non-smooth term
(cost ``c·Σt``). Every form is exact:

* ``‖a‖₁``: ``Σ a`` when ``a`` are nonnegative variables (the slacks ``ξ >= 0`` of (2.24),
  (5.15)), else ``−t <= a <= t`` with cost ``Σ t``;
* ``‖a‖∞``: ``a_j <= t`` for nonnegative variables (``‖ξ‖∞ = max_j ξ_j``), else
  ``−t <= a_j <= t``;
* ``max_j a_j``: ``a_j <= t``;
* ``‖a‖₂``: the perspective (quadratic-over-linear) form ``aᵀa / max(t, ε) − t <= 0`` with
  ``t >= 0``, plus the valid cuts ``a_j <= t`` (nonnegative variables) or ``−t <= a_j <= t``
  (``‖a‖∞ <= ‖a‖₂``), ``ε = NORM2_EPS``; why this form is in
  :mod:`balustrade.backends.casadi_backend`'s docstring (issue #12).

:meth:`Epigraph.invert` maps a point of the smooth problem back: the user's variables only
(the epigraph blocks dropped) and the *declared* cost at that point (never the epigraph
value, which may differ by solver tolerances or, for the 2-norm, by up to ``ε/4`` a term).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade.backends.passes.base import Pass
from balustrade.dsl.costs import TermKind
from balustrade.dsl.layout import Layout
from balustrade.dsl.ocp import OCP, BlockKind
from balustrade.errors import SolverError

#: the perspective form of ``‖a‖₂ <= t`` divides by ``max(t, NORM2_EPS)``
NORM2_EPS = 1e-12

#: the origin of the layout blocks this pass adds
ORIGIN = "epigraph"


@dataclass(frozen=True)
class SmoothProblem:
    """``min f(w, p)`` s.t. ``lbg <= g(w, p) <= ubg`` and the bounds of :attr:`variables`.

    ``g`` stacks the OCP's blocks (rows :attr:`block_rows`, ``n_g_user`` in all) and then
    the rows added by the pass; ``cost`` is the declared cost (for evaluation)."""

    name: str
    variables: Layout
    parameters: Layout
    w: ca.SX
    p: ca.SX
    f: ca.SX
    g: ca.SX
    lbg: np.ndarray
    ubg: np.ndarray
    block_rows: dict[str, slice]
    n_g_user: int
    cost: ca.SX


@dataclass(frozen=True)
class EpigraphInverse:
    """What :meth:`Epigraph.invert` needs: the extended layout and the declared cost as a
    function of the full primal vector and the parameters."""

    layout: Layout
    cost: ca.Function

    def primal(self, w_all: np.ndarray) -> dict[str, np.ndarray]:
        """The user's variables from the full primal vector (epigraph blocks dropped)."""
        return self.layout.unpack(w_all, user_only=True)

    def objective(self, w_all: object, p: object) -> float:
        """The declared cost at ``(w_all, p)`` (DM or arrays)."""
        return float(self.cost.call([w_all, p])[0])


class Epigraph(Pass):
    """OCP → :class:`SmoothProblem` (module docstring)."""

    name = "epigraph"

    def accepts(self, problem: object) -> bool:
        return isinstance(problem, OCP)

    def apply(self, ocp: OCP) -> tuple[SmoothProblem, EpigraphInverse]:
        layout = ocp.variable_layout
        w_user = ocp.decision_vector()
        nonneg = _nonnegative_symbols(ocp)
        f, t_syms, rows = ca.SX(0), [], []
        for idx, term in enumerate(ocp.cost.terms):
            a, c, kind = term.expr, term.coef, term.kind
            on_nonneg = kind in (TermKind.NORM1, TermKind.NORMINF, TermKind.NORM2) \
                and _all_nonneg_symbols(a, nonneg)
            if kind == TermKind.SMOOTH:
                f += c * term.expr
            elif kind == TermKind.SQUARED2:
                f += c * ca.sumsqr(a)
            elif kind == TermKind.NORM1 and on_nonneg:
                f += c * ca.sum1(a)
            elif kind in (TermKind.NORM1, TermKind.NORMINF, TermKind.MAX, TermKind.NORM2):
                size = a.numel() if kind == TermKind.NORM1 else 1
                t = ca.SX.sym(f"epi{idx}", size)
                t_syms.append(t)
                layout = layout.extend(f"epi:{idx}", (size, 1), init=0.0,
                                       lb=-np.inf if kind == TermKind.MAX else 0.0,
                                       ub=np.inf, origin=ORIGIN)
                f += c * ca.sum1(t)
                if kind == TermKind.NORM2:
                    rows.append(ca.sumsqr(a) / ca.fmax(t, NORM2_EPS) - t)
                rows.append(a - t)
                if kind != TermKind.MAX and not on_nonneg:
                    rows.append(-a - t)
            else:  # pragma: no cover - TermKind has no other members
                raise SolverError(f"{ocp.name}: unknown cost term kind {kind!r}")
        w = ca.vertcat(w_user, *t_syms)
        p = ocp.parameter_vector()
        lbg, ubg, block_rows, k = [], [], {}, 0
        for b in ocp.blocks:
            lbg.extend([0.0 if b.kind == BlockKind.EQ else -np.inf] * b.rows)
            ubg.extend([0.0] * b.rows)
            block_rows[b.name] = slice(k, k + b.rows)
            k += b.rows
        n_added = sum(int(r.numel()) for r in rows)
        lbg.extend([-np.inf] * n_added)
        ubg.extend([0.0] * n_added)
        cost = ocp.cost.expr()
        smooth = SmoothProblem(ocp.name, layout, ocp.parameter_layout, w, p, f,
                               ca.vertcat(*[b.expr for b in ocp.blocks], *rows),
                               np.array(lbg, dtype=float), np.array(ubg, dtype=float),
                               block_rows, k, cost)
        return smooth, EpigraphInverse(layout, ca.Function("objective", [w, p], [cost]))

    def invert(self, solution: tuple[np.ndarray, np.ndarray], inverse: EpigraphInverse
               ) -> tuple[dict[str, np.ndarray], float]:
        """``(w_all, p)`` of the smooth problem → ``(user primal dict, declared cost)``."""
        w_all, p = solution
        w_all = np.asarray(w_all, dtype=float).reshape(-1)
        objective = inverse.objective(w_all, p) if np.all(np.isfinite(w_all)) else np.nan
        return inverse.primal(w_all), objective


def _nonnegative_symbols(ocp: OCP) -> set:
    """Hashes of the scalar symbols of variables whose lower bounds are all ``>= 0``."""
    out = set()
    for v in ocp.variables.values():
        if np.all(v.lb >= 0):
            for k in range(v.sym.numel()):
                out.add(v.sym.nz[k].element_hash())
    return out


def _all_nonneg_symbols(a: ca.SX, nonneg_syms: set) -> bool:
    return all(a.nz[k].is_symbolic() and a.nz[k].element_hash() in nonneg_syms
               for k in range(a.numel()))
