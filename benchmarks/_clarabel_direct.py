"""Hand-written direct Clarabel formulations of the rendezvous problems (thesis Section 6.5):
(5.15), (5.16) (Algorithm 5.2) and (6.15) (Algorithm 6.4), the baselines of
``bench_robust``/``bench_horizon``.

Each problem is ``min ½wᵀPw + qᵀw`` s.t. ``Aw + s = b``, ``s ∈ K`` in Clarabel's own interface;
``P``, ``q``, ``A`` and the cones are built once; a step only writes the entries of ``b`` that
depend on the state ``x_k`` (the tube row (5.15b)), the fixed slacks of (5.16) (rows (5.16e–f))
and the bound of (6.15g), then calls ``solver.update(b=...)`` and ``solver.solve()``.

Variables, stage by stage: ``z`` (``n(N+1)``, column-major), ``v`` (``mN``), then per problem
``t`` (``mN``, the ℓ1 epigraph ``−t <= v <= t`` of ``J = Σ‖v_i‖₁``), ``ξ`` (``rN``), ``ξ_N``.

Rows: zero cone — the dynamics (5.15c); nonnegative cone — ``v_i ∈ U ⊖ KE`` (5.15d), the state
rows (5.15e) ``H z_i − ξ_i <= h − Δ_i`` (or ``H z_i <= h − Δ_i + ξ_i + ε`` in (5.16e)),
``ξ >= 0``, the epigraph rows and (6.15g) ``α_f ξ_N + 1ᵀξ <= bound``; second-order cones — the
tube (5.15b) ``‖Lᵀ(x_k − z_0)‖ <= 1`` (``P_E = LLᵀ``) and the terminal row (5.15f)
``z_Nᵀ P_f z_N <= 1 + ξ_N`` as ``‖(2L_fᵀz_N, ξ_N)‖ <= 2 + ξ_N`` (the rotated form of
``‖y‖² <= s``: ``‖(2y, s − 1)‖ <= s + 1``), in (5.16f) ``‖L_fᵀz_N‖ <= √(1 + ξ_N + ε)``.

No problem here is a QP: the tube and terminal rows are convex quadratic *constraints*
(second-order cones), so a QP solver (PIQP, OSQP) does not take them without approximation.

This module is benchmark code: it names Clarabel because it is the hand-written reference the
library is measured against, not part of the library.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import clarabel
import numpy as np
import scipy.sparse as sp


@dataclass
class RendezvousData:
    """The numbers of the rendezvous problems: dynamics, tightened sets, tube and terminal."""

    A: np.ndarray
    B: np.ndarray
    H_x: np.ndarray      # X ⊖ E rows
    h_x: np.ndarray
    H_u: np.ndarray      # U ⊖ KE rows
    h_u: np.ndarray
    deltas: np.ndarray   # Δ_i, i = 0..N−1
    P_E: np.ndarray      # tube x_k − z_0 ∈ E = {e: eᵀP_E e <= 1}
    P_f: np.ndarray      # terminal h_f(z) = zᵀP_f z − 1
    K: np.ndarray
    alpha_f: float

    @classmethod
    def from_design(cls, d: dict) -> RendezvousData:
        """From :func:`balustrade.reproduce.rendezvous.design`."""
        system, s, error, cbf = d["system"], d["setup"], d["error"], d["cbf"]
        X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
        return cls(np.asarray(system.A), np.asarray(system.B), X_E.H, X_E.h, U_E.H, U_E.h,
                   np.asarray(s.deltas(), dtype=float), error.E.P, cbf.P, error.K,
                   float(s.alpha_f))

    @property
    def N(self) -> int:
        return self.deltas.size


def _settings() -> clarabel.DefaultSettings:
    st = clarabel.DefaultSettings()
    st.verbose = False
    st.presolve_enable = False     # keep every row so that b can be updated in place
    return st


@dataclass
class _Result:
    ok: bool
    status: str
    objective: float
    w: np.ndarray
    iterations: int
    solve_time: float


class _Problem:
    """One Clarabel problem with a fixed pattern; ``solve(b)`` updates ``b`` and solves."""

    def __init__(self, P: sp.csc_matrix, q: np.ndarray, A: sp.csc_matrix, b: np.ndarray,
                 cones: list):
        self.b = b.copy()
        self.n_var, self.n_row = A.shape[1], A.shape[0]
        self.solver = clarabel.DefaultSolver(P, q, A, b, cones, _settings())

    def solve(self, b: np.ndarray) -> _Result:
        start = time.perf_counter()
        self.solver.update(b=b)
        sol = self.solver.solve()
        elapsed = time.perf_counter() - start
        status = str(sol.status)
        return _Result(status == "Solved", status, float(sol.obj_val), np.asarray(sol.x),
                       int(sol.iterations), elapsed)


class _Layout:
    """Column offsets of the variables ``z, v[, t][, ξ, ξ_N]``."""

    def __init__(self, n: int, m: int, r: int, N: int, epigraph: bool, slacks: bool):
        self.n, self.m, self.r, self.N = n, m, r, N
        self.z = 0
        self.v = n * (N + 1)
        end = self.v + m * N
        self.t = end if epigraph else None
        end += m * N if epigraph else 0
        self.xi = end if slacks else None
        end += r * N if slacks else 0
        self.xi_N = end if slacks else None
        end += 1 if slacks else 0
        self.size = end

    def z_col(self, i: int) -> int:
        return self.z + self.n * i

    def v_col(self, i: int) -> int:
        return self.v + self.m * i


class _Rows:
    """Accumulates (A block, b block) row groups of one cone."""

    def __init__(self, n_var: int):
        self.n_var = n_var
        self.blocks: list[sp.coo_matrix] = []
        self.rhs: list[np.ndarray] = []

    def add(self, entries: list[tuple[int, np.ndarray]], b: np.ndarray) -> int:
        """``entries``: (column offset, dense block) pairs sharing the rows; returns the first
        row index of the group within this cone."""
        first = sum(len(r) for r in self.rhs)
        b = np.atleast_1d(np.asarray(b, dtype=float))
        M = sp.lil_matrix((b.size, self.n_var))
        for col, block in entries:
            block = np.atleast_2d(block)
            M[:, col:col + block.shape[1]] = block
        self.blocks.append(sp.coo_matrix(M))
        self.rhs.append(b)
        return first

    @property
    def size(self) -> int:
        return sum(len(r) for r in self.rhs)

    def stacked(self) -> tuple[sp.csc_matrix, np.ndarray]:
        return sp.vstack(self.blocks).tocsc(), np.concatenate(self.rhs)


class _Builder:
    """Shared rows (5.15b–d) plus the problem-specific ones; offsets of the rows that change."""

    def __init__(self, d: RendezvousData, epigraph: bool, slacks: bool):
        self.d = d
        n, m = d.B.shape
        self.L = _Layout(n, m, d.H_x.shape[0], d.N, epigraph, slacks)
        nv = self.L.size
        self.zero, self.nonneg, self.socs = _Rows(nv), _Rows(nv), []
        L, N = self.L, d.N
        for i in range(N):                                                    # (5.15c)
            self.zero.add([(L.z_col(i + 1), np.eye(n)), (L.z_col(i), -d.A),
                           (L.v_col(i), -d.B)], np.zeros(n))
        for i in range(N):                                                    # (5.15d)
            self.nonneg.add([(L.v_col(i), d.H_u)], d.h_u)
        if epigraph:                                                          # −t <= v <= t
            for i in range(N):
                t = L.t + m * i
                self.nonneg.add([(L.v_col(i), np.eye(m)), (t, -np.eye(m))], np.zeros(m))
                self.nonneg.add([(L.v_col(i), -np.eye(m)), (t, -np.eye(m))], np.zeros(m))
        # tube (5.15b): s = [1; Lᵀx − Lᵀz_0] ∈ SOC
        self.L_E = np.linalg.cholesky(d.P_E)
        self.L_f = np.linalg.cholesky(d.P_f)
        self.tube = self._soc([(L.z_col(0), np.vstack([np.zeros((1, n)), self.L_E.T]))],
                              np.concatenate([[1.0], np.zeros(n)]))

    def _soc(self, entries, b) -> _Rows:
        rows = _Rows(self.L.size)
        rows.add(entries, b)
        self.socs.append(rows)
        return rows

    def slack_rows(self) -> None:
        """(5.15e) with ξ variables, ξ >= 0 and the rotated-cone terminal row (5.15f)."""
        d, L, n = self.d, self.L, self.L.n
        r = L.r
        for i in range(d.N):
            self.nonneg.add([(L.z_col(i), d.H_x), (L.xi + r * i, -np.eye(r))],
                            d.h_x - d.deltas[i])
        self.nonneg.add([(L.xi, -np.eye(r * d.N + 1))], np.zeros(r * d.N + 1))
        e = np.zeros((n + 2, 1))
        e[0, 0], e[-1, 0] = -1.0, -1.0
        self._soc([(L.z_col(d.N), np.vstack([np.zeros((1, n)), -2 * self.L_f.T,
                                             np.zeros((1, n))])), (L.xi_N, e)],
                  np.concatenate([[2.0], np.zeros(n + 1)]))

    def fixed_slack_rows(self) -> int:
        """(5.16e) with ξ in b; (5.16f) ``‖L_fᵀz_N‖ <= √(1 + ξ_N + ε)``; returns the first
        nonnegative row of (5.16e)."""
        d, L, n = self.d, self.L, self.L.n
        first = self.nonneg.size
        for i in range(d.N):
            self.nonneg.add([(L.z_col(i), d.H_x)], d.h_x - d.deltas[i])
        self.terminal = self._soc([(L.z_col(d.N), np.vstack([np.zeros((1, n)), -self.L_f.T]))],
                                  np.concatenate([[1.0], np.zeros(n)]))
        return first

    def problem(self, q: np.ndarray) -> tuple[_Problem, dict]:
        """The Clarabel problem (zero, nonnegative, then the second-order cones) and the first
        row of each cone."""
        Az, bz = self.zero.stacked()
        An, bn = self.nonneg.stacked()
        blocks, rhs, cones, offsets = [Az, An], [bz, bn], [], {}
        cones = [clarabel.ZeroConeT(Az.shape[0]), clarabel.NonnegativeConeT(An.shape[0])]
        row = Az.shape[0] + An.shape[0]
        offsets["nonneg"] = Az.shape[0]
        for k, soc in enumerate(self.socs):
            As, bs = soc.stacked()
            blocks.append(As)
            rhs.append(bs)
            cones.append(clarabel.SecondOrderConeT(As.shape[0]))
            offsets[f"soc{k}"] = row
            row += As.shape[0]
        A = sp.vstack(blocks).tocsc()
        P = sp.csc_matrix((self.L.size, self.L.size))
        return _Problem(P, q, A, np.concatenate(rhs), cones), offsets


class DirectRendezvous:
    """(5.15), (5.16) and (6.15) for Clarabel, built once; :meth:`alg52` and :meth:`alg64` are
    the per-step baselines (only ``b`` changes between steps)."""

    EPS = 1e-6   # the ε of (5.16e–f), as in balustrade's robust_pcbf_filter_problem

    def __init__(self, d: RendezvousData):
        self.d = d
        self.last_iterations = 0   # interior-point iterations of the last alg52/alg64 call
        # (5.15): min α_f ξ_N + Σ 1ᵀξ_i
        b1 = _Builder(d, epigraph=False, slacks=True)
        b1.slack_rows()
        q = np.zeros(b1.L.size)
        q[b1.L.xi:b1.L.xi_N] = 1.0
        q[b1.L.xi_N] = d.alpha_f
        self.slack, off = b1.problem(q)
        self._slack_tube = off["soc0"] + 1
        self.L1, self.L_E = b1.L, b1.L_E
        # (5.16): min Σ‖v_i‖₁ with the slacks fixed
        b2 = _Builder(d, epigraph=True, slacks=False)
        first = b2.fixed_slack_rows()
        q = np.zeros(b2.L.size)
        q[b2.L.t:b2.L.t + b2.L.m * d.N] = 1.0
        self.filter, off = b2.problem(q)
        self._filter_tube = off["soc0"] + 1
        self._filter_state = off["nonneg"] + first
        self._filter_term = off["soc1"]
        self.L2 = b2.L
        # (6.15): min Σ‖v_i‖₁ s.t. (5.15b–f) and α_f ξ_N + 1ᵀξ <= bound
        b3 = _Builder(d, epigraph=True, slacks=True)
        b3.slack_rows()
        g = np.ones((1, b3.L.r * d.N + 1))
        g[0, -1] = d.alpha_f
        self._mo_bound = b3.nonneg.add([(b3.L.xi, g)], np.zeros(1))
        q = np.zeros(b3.L.size)
        q[b3.L.t:b3.L.t + b3.L.m * d.N] = 1.0
        self.mo, off = b3.problem(q)
        self._mo_tube = off["soc0"] + 1
        self._mo_bound += off["nonneg"]
        self.L3 = b3.L

    # -- helpers ---------------------------------------------------------------------------
    def _tube_b(self, prob: _Problem, row: int, x: np.ndarray) -> None:
        prob.b[row:row + x.size] = self.L_E.T @ x

    def _z(self, L: _Layout, w: np.ndarray) -> np.ndarray:
        return w[L.z:L.v].reshape(L.N + 1, L.n).T

    def _v(self, L: _Layout, w: np.ndarray) -> np.ndarray:
        return w[L.v:L.v + L.m * L.N].reshape(L.N, L.m).T

    def minimal_slacks(self, z: np.ndarray) -> tuple[np.ndarray, float]:
        """``ξ_i = max(0, H z_i − h + Δ_i)``, ``ξ_N = max(0, z_NᵀP_f z_N − 1)``."""
        d = self.d
        xi = np.maximum(0.0, d.H_x @ z[:, :d.N] - d.h_x[:, None] + d.deltas[None, :])
        return xi, max(0.0, float(z[:, d.N] @ d.P_f @ z[:, d.N]) - 1.0)

    def applied(self, x: np.ndarray, z: np.ndarray, v: np.ndarray) -> np.ndarray:
        return v[:, 0] + self.d.K @ (x - z[:, 0])

    # -- the problems ----------------------------------------------------------------------
    def solve_slack(self, x: np.ndarray) -> tuple[_Result, np.ndarray, np.ndarray]:
        """(5.15) at ``x``: (result, z, v)."""
        self._tube_b(self.slack, self._slack_tube, x)
        r = self.slack.solve(self.slack.b)
        return r, self._z(self.L1, r.w), self._v(self.L1, r.w)

    def solve_filter(self, x: np.ndarray, xi: np.ndarray, xi_N: float
                     ) -> tuple[_Result, np.ndarray, np.ndarray]:
        """(5.16) at ``x`` with the slacks ``ξ`` (``r × N``) and ``ξ_N`` fixed."""
        d, p = self.d, self.filter
        self._tube_b(p, self._filter_tube, x)
        rows = d.h_x[:, None] - d.deltas[None, :] + np.asarray(xi) + self.EPS
        p.b[self._filter_state:self._filter_state + rows.size] = rows.T.reshape(-1)
        p.b[self._filter_term] = np.sqrt(1.0 + xi_N + self.EPS)
        r = p.solve(p.b)
        return r, self._z(self.L2, r.w), self._v(self.L2, r.w)

    def solve_mo(self, x: np.ndarray, bound: float) -> tuple[_Result, np.ndarray, np.ndarray]:
        """(6.15) at ``x`` with the right side ``bound`` of (6.15g)."""
        p = self.mo
        self._tube_b(p, self._mo_tube, x)
        p.b[self._mo_bound] = bound
        r = p.solve(p.b)
        return r, self._z(self.L3, r.w), self._v(self.L3, r.w)

    def alg52(self, x: np.ndarray) -> tuple[bool, np.ndarray | None, float, float]:
        """One Algorithm 5.2 step: (5.15), the minimal slacks of its ``z`` (the polishing of
        balustrade), (5.16); returns (both solved, applied input, ``h_r``, fuel of (5.16))."""
        r1, z1, _ = self.solve_slack(x)
        self.last_iterations = r1.iterations
        if not r1.ok:
            return False, None, float("nan"), float("nan")
        xi, xi_N = self.minimal_slacks(z1)
        h_r = float(xi.sum()) + self.d.alpha_f * xi_N   # h~ of the minimal slacks, as balustrade
        r2, z2, v2 = self.solve_filter(x, xi, xi_N)
        self.last_iterations += r2.iterations
        if not r2.ok:
            return False, None, h_r, float("nan")
        return True, self.applied(x, z2, v2), h_r, r2.objective

    def alg64(self, x: np.ndarray, bound: float) -> tuple[bool, np.ndarray | None, float]:
        """One (6.15) solve; returns (solved, applied input, fuel objective)."""
        r, z, v = self.solve_mo(x, bound)
        self.last_iterations = r.iterations
        if not r.ok:
            return False, None, float("nan")
        return True, self.applied(x, z, v), r.objective
