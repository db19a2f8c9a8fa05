"""A hot-started dual active-set engine for small dense LPs/QPs of the direct backend:
DAQP through its own Python interface (``daqp.Model``), kept across solves, with every
answer checked and PIQP behind it (issue #15; docs/adaptive.md, "Session 14: DAQP's own
interface").

The QP is the direct backend's lowered one (:class:`~balustrade.backends.passes.to_conic.
ConicProgram`): ``min ½yᵀPy + qᵀy`` s.t. ``A_eq y = b_eq`` (the zero-cone rows) and
``A_in y <= b_in``. DAQP holds it densely (``H`` ``n × n``, ``A`` ``m × n``). The model is set
up once (the first solve starts cold); every later solve only updates ``f = q``, the bounds
and, when they changed, the values of ``A(p)`` (e.g. the ``s_jr`` constants of (4.5) when
``Θ_k`` changes, thesis eq. (4.5c)), and DAQP starts from the working set of the previous
solve — the hot start of consecutive steps of Algorithm 4.1. A positive semidefinite ``P``
(the cost of (4.5) weighs ``v_0 − u_p`` only) is handled by DAQP's proximal-point outer
iterations; their stopping test is set tight (``eta_prox``), as is the primal tolerance.

**No answer is taken on DAQP's word.** A solve counts as ``optimal`` only when DAQP's exit
flag is 1 (optimal) *and* the KKT conditions of the lowered QP hold at its point and
multipliers to :data:`KKT_TOL` (:func:`kkt_residual`: stationarity, primal feasibility,
the multipliers' signs, complementarity, each scaled by its own row's or entry's size).
Anything else —
any other flag (DAQP's "infeasible" carries no certificate the backend could check, its
cycling/iteration-limit/non-convexity flags no answer) or a residual above the tolerance —
is solved again by PIQP (the direct backend's QP engine, :class:`~balustrade.backends.
direct_engines.PiqpEngine`), whose result is returned with both solvers' words; the count is
kept in :attr:`DaqpEngine.fallbacks`. After a fallback the model is set up again, hot from
PIQP's point when PIQP found one.

Unlike the interior-point engines, the point DAQP returns depends on the previous solve
(its working set): on a QP with a non-unique minimizer (the semidefinite ``P`` of (4.5))
two histories can give different optimal points of the same optimal face with the same
objective; the inputs ``v_0`` of (4.5) are unique (strictly convex cost in them).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from balustrade.backends.passes.to_conic import ConicProgram
from balustrade.backends.solution import Status
from balustrade.errors import SolverError

#: KKT residual (scaled) below which a DAQP "optimal" is accepted
KKT_TOL = 1e-8
#: DAQP settings of the engine: a tight primal tolerance (its default 1e-6 let the objective
#: of (4.5) drop 1.3e-5 below PIQP's) and a tight stopping test of the proximal outer
#: iterations (the default stopped after one outer iteration with stationarity residuals
#: of 2e-7 on 25 of 149 closed-loop solves of (4.5), 3 masses); measured in
#: docs/adaptive.md, "Session 14"
DEFAULT_OPTIONS = {"primal_tol": 1e-10, "eta_prox": 1e-12}
#: the largest ``m · n`` (entries of the dense constraint matrix) the engine accepts: DAQP
#: is dense, and (4.5) of 8 masses (28980 × 587, 136 MB) is far beyond what it solves fast
DENSE_LIMIT = 2_000_000
#: DAQP's exit flags (``include/constants.h`` of DAQP)
EXIT_WORDS = {1: "optimal", 2: "soft optimal", -1: "infeasible", -2: "cycling",
              -3: "unbounded", -4: "iteration limit", -5: "nonconvex",
              -6: "overdetermined initial working set", -7: "time limit",
              -8: "unsupported"}
#: DAQP's sense flag of an equality row (active and immutable)
_EQUALITY = 5
#: DAQP's infinite bound
_INF = 1e30


def row_norms(A: sp.spmatrix) -> np.ndarray:
    """``max_j |A_ij|`` per row, 1 for a zero row: the unit :func:`kkt_residual` measures each
    row in."""
    norms = np.asarray(abs(sp.csr_matrix(A)).max(axis=1).todense(), dtype=float).ravel()
    return np.where(norms > 0, norms, 1.0)


def kkt_residual(P: sp.spmatrix, q: np.ndarray, A: sp.spmatrix, b: np.ndarray, m0: int,
                 y: np.ndarray, z: np.ndarray, AT: sp.spmatrix | None = None,
                 norms: np.ndarray | None = None) -> float:
    """Largest scaled KKT violation of ``min ½yᵀPy + qᵀy, A[:m0] y = b[:m0], A[m0:] y <= b[m0:]``
    at the point ``y`` and multipliers ``z`` (``P y + q + Aᵀz = 0``, ``z >= 0`` on the
    inequality rows). ``nan`` when any of them is not finite, or a ``b_i`` is NaN or ``−∞``
    (no point satisfies that row). ``AT``: ``Aᵀ`` if the caller keeps it (else formed here);
    ``norms``: :func:`row_norms` of ``A`` if the caller keeps them.

    Each row is measured in its own unit first: row ``i`` divided by ``n_i = max_j |A_ij|``
    (its multiplier multiplied by it), so that the check does not depend on how a row is
    scaled — a row ``10⁻⁹ aᵀy = 10⁻⁹ β`` missed by a distance 1 is a residual 10⁻⁹ unscaled,
    which passed the tolerance (audit E, session 15). Each error is then scaled by the size
    of its own terms, never by the largest entry of the whole problem (one loose row
    ``|b_i| = 10⁶`` must not loosen the tolerance of the others):

    * primal feasibility and complementarity of row ``i``: ``/ (1 + |b_i| / n_i)`` (an
      infinite ``b_i = +∞`` is no row: neither error counts there, and its multiplier must
      be 0: counted with the signs);
    * stationarity, entry ``j``: ``/ (1 + max(|q_j|, |(P y)_j|, |(Aᵀz)_j|))`` — elementwise,
      for the same reason as per row (a large ``q_j`` of one variable leaves the others at
      the tight tolerance);
    * the multipliers' signs (``n_i z_i < 0`` on an inequality row, ``n_i z_i ≠ 0`` on a row
      ``b_i = +∞``): ``/ (1 + max |Aᵀz|, |q|, |P y|)`` — a multiplier's size is measured
      against the gradient it balances."""
    b = np.asarray(b, dtype=float)
    if np.any(np.isnan(b) | (b == -np.inf)):
        return float("nan")
    n_i = row_norms(A) if norms is None else norms
    r = (A @ y - b) / n_i
    finite = np.isfinite(b)
    row_scale = 1.0 + np.abs(np.where(finite, b, 0.0)) / n_i
    Py = P @ y
    ATz = (A.T if AT is None else AT) @ z
    zn = z * n_i
    mags = np.maximum(np.maximum(np.abs(q), np.abs(Py)), np.abs(ATz))
    stat = np.max(np.abs(Py + q + ATz) / (1.0 + mags), initial=0.0)
    prim = max(np.max(np.abs(r[:m0]) / row_scale[:m0], initial=0.0),
               np.max(np.where(finite[m0:], r[m0:], 0.0) / row_scale[m0:], initial=0.0))
    wrong = np.where(finite[m0:], np.maximum(-zn[m0:], 0.0), np.abs(zn[m0:]))
    dual = np.max(wrong, initial=0.0) / (1.0 + np.max(mags, initial=0.0))
    comp = np.max(np.abs(zn[m0:] * np.where(finite[m0:], r[m0:], 0.0)) / row_scale[m0:],
                  initial=0.0)
    worst = max(stat, prim, dual, comp)
    return float(worst) if np.isfinite(worst) else float("nan")


def _real(v: object) -> bool:
    """``v`` an int or float (numpy's included), not a bool."""
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool)


class DaqpEngine:
    """``daqp.Model`` kept across solves for an LP/QP of at most :data:`DENSE_LIMIT` dense
    entries; :meth:`run` updates ``q``, ``b`` (and the values of ``A`` when given and
    changed), solves hot, checks the KKT conditions and falls back to PIQP (module
    docstring). ``options``: DAQP settings (``daqp.Model().settings`` keys) over
    :data:`DEFAULT_OPTIONS`, and ``kkt_tol`` (default :data:`KKT_TOL`)."""

    name = "daqp"

    def __init__(self, prog: ConicProgram, options: dict, P: sp.csc_matrix | None = None,
                 q: np.ndarray | None = None):
        try:
            import daqp
        except ImportError:
            raise SolverError("direct backend: the solver 'daqp' (target 'fast-convex-daqp') "
                              "needs the package daqp: pip install 'balustrade[daqp]'") from None
        if prog.conic:
            raise SolverError("direct backend: DAQP takes LPs and QPs only; this problem "
                              "needs a second-order cone (use solver 'clarabel')")
        m, n = prog.A.shape
        if m * n > DENSE_LIMIT:
            raise SolverError(f"direct backend: DAQP is dense and this problem's constraint "
                              f"matrix is {m} x {n} ({m * n} entries > {DENSE_LIMIT}); use "
                              "'fast-convex' (PIQP, sparse) or 'fast-convex-rowgen'")
        options = dict(options)
        tol = options.pop("kkt_tol", KKT_TOL)
        # a real number, finite and > 0: an infinite (or a string's, a bool's) tolerance
        # would accept every "optimal" of DAQP unchecked (audit E)
        if not _real(tol) or not (np.isfinite(tol) and tol > 0):
            raise SolverError(f"direct backend: DAQP option 'kkt_tol' must be a finite "
                              f"number > 0, got {tol!r}")
        self.kkt_tol = float(tol)
        known = daqp.Model().settings
        unknown = sorted(str(k) for k in options if k not in known)
        if unknown:
            raise SolverError(f"direct backend: unknown DAQP option(s) {', '.join(unknown)}; "
                              f"use {', '.join(sorted(known))} or kkt_tol")
        odd = sorted(str(k) for k, v in options.items() if not _real(v) or np.isnan(v))
        if odd:
            raise SolverError(f"direct backend: DAQP option(s) {', '.join(odd)} must be real "
                              f"numbers, got {', '.join(repr(options[k]) for k in odd)}")
        self.settings = {**DEFAULT_OPTIONS, **options}
        self._daqp = daqp
        self.prog, self.m0, self.n = prog, sum(k for kind, k in prog.cones if kind == "zero"), n
        upper = sp.triu(sp.csc_matrix(prog.P if P is None else P))   # P as the solvers
        Pm = (upper + sp.triu(upper, 1).T).tocsc()                    # read it: its upper part
        self.P = Pm
        self.H = np.ascontiguousarray(Pm.toarray())
        self._pattern = sp.csc_matrix(prog.A)
        self._pattern.sort_indices()
        cols = np.repeat(np.arange(n), np.diff(self._pattern.indptr))
        self._flat = self._pattern.indices * n + cols      # where A.data sits in the dense A
        #: ``A(p)`` on the program's pattern; its ``data`` are the values DAQP holds
        self._A = sp.csc_matrix((np.array(self._pattern.data, dtype=float),
                                 self._pattern.indices, self._pattern.indptr),
                                shape=self._pattern.shape)
        self._values = self._A.data
        self._AT = self._A.T                # a CSR view on the same values
        self._norms = row_norms(self._A)    # kkt_residual's row units, kept current
        self._dense = np.zeros(m * n)
        self._dense[self._flat] = self._values
        self.sense = np.zeros(m, dtype=np.intc)
        self.sense[:self.m0] = _EQUALITY
        self.model = None                  # set up at the first solve (cold)
        #: DAQP's exit flag and the KKT residual (``nan`` if not computed) of the last solve
        self.last: tuple[int | None, float] = (None, float("nan"))
        self._start: np.ndarray | None = None   # primal start of the next set-up
        self._piqp = None                  # the fallback, built on its first use
        #: solves answered by PIQP because DAQP's answer was not verified
        self.fallbacks = 0
        #: solves whose DAQP answer passed the checks
        self.verified = 0

    def _check(self, q: np.ndarray, b: np.ndarray, A: np.ndarray | None) -> None:
        m = self._pattern.shape[0]
        for name, v, size in (("q", q, self.n), ("b", b, m),
                              ("A values", A, self._values.size)):
            if v is not None and np.shape(v) != (size,):
                raise SolverError(f"direct backend (DAQP): {name} must have shape ({size},), "
                                  f"got {np.shape(v)}")

    def _bounds(self, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        upper = np.where(np.isfinite(b), b, _INF)
        lower = np.full(b.size, -_INF)
        lower[:self.m0] = upper[:self.m0]
        return upper, lower

    def _setup(self, q: np.ndarray, b: np.ndarray) -> int:
        upper, lower = self._bounds(b)
        self.model = self._daqp.Model()
        self.model.settings = self.settings
        extra = {} if self._start is None else {"primal_start": self._start}
        flag, _ = self.model.setup(self.H, np.array(q, dtype=float),
                                   self._dense.reshape(-1, self.n), upper, lower,
                                   self.sense.copy(), **extra)
        self._start = None
        if flag < 0:
            self.model = None
        return flag

    def run(self, q: np.ndarray, b: np.ndarray, A: np.ndarray | None = None):
        """Solve with ``q``, ``b`` (and the values ``A`` of ``A(p)`` on the program's
        pattern): DAQP hot from the last working set; PIQP when DAQP's answer is not
        verified."""
        from balustrade.backends.direct_engines import RawResult

        self._check(q, b, A)
        self.last = (None, float("nan"))
        changed = A is not None and not np.array_equal(A, self._values)
        if changed:
            self._values[:] = A
            self._dense[self._flat] = self._values
            self._norms = row_norms(self._A)
        if self.model is None:
            flag = self._setup(q, b)
            if flag < 0:
                return self._fallback(q, b, f"DAQP: set-up failed, flag {flag} "
                                            f"({EXIT_WORDS.get(flag, 'unknown')})")
        else:
            upper, lower = self._bounds(b)
            data = {"f": np.array(q, dtype=float), "bupper": upper, "blower": lower}
            if changed:
                data["A"] = self._dense.reshape(-1, self.n)
            flag = self.model.update(**data)
            if flag < 0:
                self.model = None
                return self._fallback(q, b, f"DAQP: update failed, flag {flag} "
                                            f"({EXIT_WORDS.get(flag, 'unknown')})")
        x, _, flag, info = self.model.solve()
        self.last = (flag, float("nan"))
        iterations = int(info["iterations"])
        words = f"DAQP: {EXIT_WORDS.get(flag, 'unknown')} (flag {flag})"
        if flag != 1:
            return self._fallback(q, b, words, iterations)
        z = np.asarray(info["lam"], dtype=float)
        kkt = kkt_residual(self.P, q, self._A, b, self.m0, x, z, self._AT, self._norms)
        self.last = (flag, kkt)
        if not kkt <= self.kkt_tol:
            return self._fallback(q, b, f"{words}, KKT residual {kkt:.1e} > "
                                        f"{self.kkt_tol:g}", iterations)
        self.verified += 1
        return RawResult(Status.OPTIMAL, f"{words}, KKT residual {kkt:.1e}", x, z, iterations)

    def _matrix(self) -> sp.csc_matrix:
        """``A(p)`` with the values of the last solve (built once, values kept current)."""
        return self._A

    def _fallback(self, q: np.ndarray, b: np.ndarray, why: str, iterations: int = 0):
        """PIQP's answer in place of DAQP's unverified one; the model is set up again at
        the next solve (from PIQP's point when it has one)."""
        from balustrade.backends.direct_engines import PiqpEngine

        if self._piqp is None:
            self._piqp = PiqpEngine(self.prog, {}, P=self.P, q=q)
        self.fallbacks += 1
        raw = self._piqp.run(q, b, self._values)
        raw.words = f"{raw.words} (fallback: {why})"
        raw.iterations += iterations
        raw.solver = "piqp"            # who answered: Solution.solver and RAPSF.engine say so
        self.model = None
        self._start = raw.y.copy() if raw.status.success and raw.y is not None else None
        return raw


#: the C library of the engine's solver in the casadi wheel (``<casadi>/libdaqp.so``, headers
#: in ``<casadi>/include/daqp``), linked by the emitted hot-started step
C_LIBRARY = "daqp"
#: settings of the emitted C. The wheel's library is DAQP 0.5.0 (its headers equal the
#: v0.5.0 tag of darnstrom/daqp), not the 0.11 of the Python engine: it has no automatic
#: semi-proximal term for a singular ``H`` (its ``eps_prox`` is added to every diagonal
#: entry) and its proximal loop restarts every solve from ``x = 0``. The emitted C therefore
#: runs the proximal-point iterations itself (``bal/rapsf_hot.c``): weight ``prox`` on the
#: zero diagonal entries of ``P`` only, centre the last answer, at most ``prox_iter``
#: iterations, each stopped by the KKT check. Measured on 150 recorded 3-mass (4.5)
#: (docs/deploy_c.md, "Session 15"): weights 1e-2 … 3e-5 all verified (worst 8.8e-9),
#: 1e-3 at 0.31 ms against 0.52 ms for the library's loop with ``eps_prox`` 1e-3
C_OPTIONS = {"primal_tol": 1e-10, "prox": 1e-3, "prox_iter": 30}


def lowered_for_c(compiled: object) -> dict | None:
    """The lowered QP of a problem compiled on the direct backend with this engine, as data
    for emitted C (``None`` when ``compiled`` is something else): ``P`` (CSC, full
    symmetric), ``q0``, ``Q`` (CSR: ``q = q0 + Q p``), ``b0``, ``B`` (``b = b0 + B p``), ``A``
    (CSC pattern with its constant values), ``A_param`` (CSR, one row per value of ``A``;
    zero rows when ``A`` does not depend on ``p``), ``m0`` equality rows, ``n_w``, the
    cost function ``objective(w, p)``, the library, the C settings and the KKT tolerance.
    Refused (:class:`SolverError`): rows set aside for their large bounds, bounds computed
    by functions of ``p``, row generation — a solve of those is more than one QP."""
    engine = getattr(compiled, "engine", None)
    if not isinstance(engine, DaqpEngine):
        return None
    prog = compiled.program
    name = getattr(getattr(compiled, "ocp", None), "name", "problem")
    if prog.large is not None or prog.derived or getattr(compiled, "rowgen", None) is not None:
        raise SolverError(f"{name}: the emitted hot-started QP needs one QP per solve; this "
                          "program has rows with large bounds, bounds computed from functions "
                          "of the parameters, or row generation")
    A = sp.csc_matrix(prog.A)
    if not A.has_sorted_indices:
        raise SolverError(f"{name}: the lowered constraint matrix has unsorted indices")
    n_p = prog.Q.shape[1]
    A_param = sp.csr_matrix(prog.A_param) if prog.A_param is not None else \
        sp.csr_matrix((A.nnz, n_p))
    return {"P": sp.csc_matrix(engine.P), "q0": np.asarray(prog.q0, dtype=float),
            "Q": sp.csr_matrix(prog.Q), "b0": np.asarray(prog.b0, dtype=float),
            "B": sp.csr_matrix(prog.B), "A": A, "A_param": A_param, "m0": engine.m0,
            "n_w": prog.n_w, "objective": prog.objective,
            "library": C_LIBRARY, "options": dict(C_OPTIONS),
            "kkt_tol": engine.kkt_tol}
