"""The Chronos race car example of thesis §8.4 (SPEC §2.33, §3.8): PCBF design.

* :func:`steady_states` — the steady cornering points on the centre line (``e = 0``,
  ``v_x = 1`` m/s) of the progress-independent dynamics
  (:func:`~balustrade.models.chronos.lateral_ode`) for 21 curvature values spanning the
  track's ``κ`` range, with their Euler (20 ms) linearizations.
* :func:`terminal_cbf_sdp` — ONE synthesis problem (the synthesis language) for a common
  quadratic Lyapunov function ``V(Δz) = Δzᵀ P Δz`` and gain ``K`` of all 21 linearizations
  (21 vertex invariance blocks ``[[λE, (A_jE + B_jY)ᵀ], [A_jE + B_jY, E]] ⪰ 0``, ``P = E⁻¹``,
  ``K = YP``), with the 1-sublevel set inside the (linearized) corner constraints (8.6) and
  the inputs, for every vertex. ``Δz = z − z_ss(κ(s))`` is the deviation of
  ``z = [e, μ, v_x, v_y, ω]`` from the steady cornering point at the local curvature, so
  the ellipsoid moves with the track (a design choice: the thesis names the procedure
  of [171] but not its centring; with a fixed centre the cornering equilibria,
  ``ω ≈ 1.67`` rad/s, are not equilibria of the straight-line design).
* :class:`ChronosTerminalCBF` — ``h_f(x) = V(Δz(x)) − 0.99`` (SPEC [Default] reading of
  the 0.99-sublevel set) and ``π_f(x) = u_ss(κ(s)) + KΔz``; ``z_ss``, ``u_ss`` are cubic
  fits in ``κ`` of the 21 steady states.
* :func:`check_invariance` — randomly initialized NLPs (as the thesis does): the largest
  constraint value and input-bound value of ``π_f`` on ``D_f = {V <= 1}`` and
  ``h_f(f(x, π_f(x)))`` on ``S_f``, each maximized from random starts through the
  ``"exact"`` target. Local maxima: evidence, not a proof.
* :func:`chronos_design` / :func:`chronos_problems` — the PCBF (2.24) with ``N = 50``,
  ``α_f = 10``, ``Δ_i = i·10⁻⁴`` on the Euler Frenet model, and the compiled pair
  (2.24)/(7.8) the sampler needs (``balustrade sample --problem chronos``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade._checks import as_count, as_scalar
from balustrade.backends import compile, solve_synthesis
from balustrade.dsl import OCP
from balustrade.dsl.sets import Box
from balustrade.dsl.sets_function import FunctionSet
from balustrade.dsl.synthesis import SynthesisProblem, bmat, logdet
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError
from balustrade.learn.sampler import PCBFProblems, compile_pair
from balustrade.models.chronos import (
    TABLE_8_1,
    TS,
    ChronosParams,
    chronos_frenet,
    chronos_sets,
    constraint_values,
    lateral_ode,
)
from balustrade.models.track import Track, oval
from balustrade.problems.pcbf import extended_pcbf_problem, pcbf_slack_problem

#: the design speed (m/s), the number of curvature vertices, the safe level of §8.4
V_DESIGN, N_KAPPA, LEVEL = 1.0, 21, 0.99
#: extra bounds on the deviation from the steady state (v_x, v_y, ω, μ) that keep the
#: ellipsoid where the linearization is meaningful (design choice, not in the thesis)
DEVIATION_BOUNDS = {2: 0.3, 3: 0.15, 4: 1.0, 1: 0.3}
#: margin (m) on the linearized corner rows (``sin μ ≈ μ``, ``cos μ ≈ 1``)
CORNER_MARGIN = 0.01
#: input rows of the design tightened by this much: ``π_f`` interpolates ``u_ss(κ)`` between
#: the 21 design curvatures, where the vertex rows alone let ``T`` reach −5e-6 on
#: ``D_f = {V <= 1}`` (found by :func:`check_invariance`)
INPUT_MARGIN = 1e-3
POLY_DEGREE = 3
#: ``λ`` of the invariance LMIs: with 0.99 the random NLPs found ``h_f(f(x, π_f(x))) ≈ 4e-3
#: > 0`` on ``∂S_f`` (nonlinearity); 0.95 leaves a margin (no counterexample found)
DECREASE = 0.95


@dataclass
class SteadyStates:
    """Steady cornering on the centre line at ``v_x = V_DESIGN`` for curvatures ``kappa``:
    ``z[j] = [0, μ, v_x, v_y, ω]``, ``u[j] = [T, δ]`` and the Euler linearizations
    ``A[j]``, ``B[j]`` (step ``ts``) of :func:`~balustrade.models.chronos.lateral_ode`."""

    kappa: np.ndarray
    z: np.ndarray
    u: np.ndarray
    A: np.ndarray
    B: np.ndarray


def steady_states(kappa: object, params: ChronosParams = TABLE_8_1, ts: float = TS,
                  vx: float = V_DESIGN) -> SteadyStates:
    """Solve ``ė = μ̇ = v̇_x = v̇_y = ω̇ = 0`` at ``e = 0``, ``v_x = vx`` for
    ``(μ, v_y, ω, T, δ)`` at every curvature (Newton via CasADi's rootfinder)."""
    kappa = np.atleast_1d(np.asarray(kappa, dtype=float))
    z, u = ca.SX.sym("z", 5), ca.SX.sym("u", 2)
    y = ca.SX.sym("y", 5)
    zs, us, As, Bs = [], [], [], []
    guess = np.array([0.0, 0.0, 0.0, 0.3, 0.0])
    for k in kappa:
        f = lateral_ode(float(k), params)
        zz = ca.vertcat(0.0, y[0], vx, y[1], y[2])
        root = ca.rootfinder("steady", "newton", ca.Function("g", [y], [f(zz, y[3:])]),
                             {"abstol": 1e-12})
        guess = np.array(root(guess)).reshape(-1)
        zk = np.array([0.0, guess[0], vx, guess[1], guess[2]])
        uk = guess[3:].copy()
        res = np.array(ca.Function("f", [z, u], [f(z, u)])(zk, uk)).reshape(-1)
        if np.max(np.abs(res)) > 1e-8:
            raise BalustradeError(f"steady_states: no steady cornering at kappa = {k:g} "
                                  f"(residual {np.max(np.abs(res)):.2g})")
        jac = ca.Function("J", [z, u], [ca.jacobian(f(z, u), z), ca.jacobian(f(z, u), u)])
        A, B = jac(zk, uk)
        zs.append(zk)
        us.append(uk)
        As.append(np.eye(5) + ts * np.asarray(A))
        Bs.append(ts * np.asarray(B))
    return SteadyStates(kappa, np.array(zs), np.array(us), np.array(As), np.array(Bs))


def _rows(ss: SteadyStates, params: ChronosParams, U: Box
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """State rows ``a·Δz <= b`` valid at every vertex (``b = min_j (b̄ − a·z_ss,j)``) and
    input rows ``a·Δu <= b`` likewise."""
    half = 0.5 * params.w_track - 0.5 * params.w_veh - CORNER_MARGIN
    H, h = [], []
    for sgn in (1.0, -1.0):
        a = sgn * np.array([1.0, params.l_f, 0.0, 0.0, 0.0])
        H.append(a)
        h.append(min(half - a @ z for z in ss.z))
    for i, bound in DEVIATION_BOUNDS.items():
        for sgn in (1.0, -1.0):
            a = np.zeros(5)
            a[i] = sgn
            H.append(a)
            h.append(bound)
    Hu = np.vstack([np.eye(2), -np.eye(2)])
    hu = np.array([min(U.ub[i] - u[i] for u in ss.u) for i in range(2)] +
                  [min(u[i] - U.lb[i] for u in ss.u) for i in range(2)]) - INPUT_MARGIN
    return np.array(H), np.array(h), Hu, hu


def terminal_cbf_sdp(ss: SteadyStates, params: ChronosParams = TABLE_8_1,
                     decrease_factor: float = DECREASE) -> SynthesisProblem:
    """The §8.4 terminal-CBF design as one synthesis problem (module docstring):
    ``min −log det E`` s.t. 21 vertex invariance LMIs, state rows and input rows."""
    lam = as_scalar(decrease_factor, "terminal_cbf_sdp: decrease_factor", 0.0, 1.0,
                    low_open=True)
    _, U = chronos_sets(params)
    H, h, Hu, hu = _rows(ss, params, U)
    if np.any(h <= 0) or np.any(hu <= 0):
        raise BalustradeError(f"terminal_cbf_sdp: the steady states violate the constraints "
                              f"(state bounds {h}, input bounds {hu})")
    sdp = SynthesisProblem("Chronos terminal CBF (§8.4)")
    E = sdp.matrix("E", (5, 5), symmetric=True)
    Y = sdp.matrix("Y", (2, 5))
    for j, (A, B) in enumerate(zip(ss.A, ss.B)):
        M = A @ E + B @ Y
        sdp.lmi(f"invariance kappa_{j}", bmat([[lam * E, M.T], [M, E]]))
    for i, (a, b) in enumerate(zip(H, h)):
        sdp.lmi(f"state row {i}", bmat([[b ** 2, a[None] @ E], [(a[None] @ E).T, E]]))
    for i, (a, b) in enumerate(zip(Hu, hu)):
        sdp.lmi(f"input row {i}", bmat([[b ** 2, a[None] @ Y], [(a[None] @ Y).T, E]]))
    sdp.minimize(-logdet(E))
    return sdp


@dataclass
class ChronosTerminalCBF:
    """``h_f(x) = Δzᵀ P Δz − level`` with ``Δz = [e, μ, v_x, v_y, ω] − z_ss(κ(s))`` and
    ``π_f(x) = u_ss(κ(s)) + K Δz`` on the Frenet state ``x = [s, e, μ, v_x, v_y, ω]``."""

    P: np.ndarray
    K: np.ndarray
    track: Track
    z_coef: np.ndarray  # (degree+1, 5), highest power first
    u_coef: np.ndarray  # (degree+1, 2)
    level: float = LEVEL
    status: str = "optimal"
    steady: SteadyStates | None = field(default=None, repr=False)

    def _poly(self, coef: np.ndarray, k: object) -> object:
        out = 0 * k + coef[0]
        for c in coef[1:]:
            out = out * k + c
        return out

    def _parts(self, x: object) -> tuple[object, object]:
        sym = isinstance(x, (ca.SX, ca.MX))
        if sym:
            k = self.track.kappa(x[0])
            zs = ca.vertcat(*[self._poly(self.z_coef[:, i], k) for i in range(5)])
            us = ca.vertcat(*[self._poly(self.u_coef[:, i], k) for i in range(2)])
            return x[1:6] - zs, us
        x = np.asarray(x, dtype=float).reshape(-1)
        k = self.track.curvature(x[0])
        zs = np.array([self._poly(self.z_coef[:, i], k) for i in range(5)])
        us = np.array([self._poly(self.u_coef[:, i], k) for i in range(2)])
        return x[1:6] - zs, us

    def V(self, x: object) -> object:
        dz, _ = self._parts(x)
        if isinstance(dz, (ca.SX, ca.MX)):
            return ca.mtimes([dz.T, ca.DM(self.P), dz])
        return float(dz @ self.P @ dz)

    def __call__(self, x: object) -> object:
        return self.V(x) - self.level

    def policy(self, x: object) -> object:
        dz, us = self._parts(x)
        if isinstance(dz, (ca.SX, ca.MX)):
            return us + ca.mtimes(ca.DM(self.K), dz)
        return us + self.K @ dz


def chronos_terminal_cbf(track: Track | None = None, params: ChronosParams = TABLE_8_1,
                         target: object = "sdp", decrease_factor: float = DECREASE
                         ) -> ChronosTerminalCBF:
    """Solve :func:`terminal_cbf_sdp` for the curvature range of ``track`` (21 values from
    ``min κ`` to ``max κ``) and build the terminal CBF."""
    track = oval() if track is None else track
    k = track.curvature(np.linspace(0.0, track.length, 4001))
    kappa = np.linspace(float(np.min(k)), float(np.max(k)), N_KAPPA)
    ss = steady_states(kappa, params)
    sol = solve_synthesis(terminal_cbf_sdp(ss, params, decrease_factor), target)
    if not sol.ok:
        raise BalustradeError(f"chronos_terminal_cbf: SDP not solved ({sol.status}: "
                              f"{sol.message})")
    E = 0.5 * (sol.values["E"] + sol.values["E"].T)
    P = np.linalg.inv(E)
    P = 0.5 * (P + P.T)
    K = sol.values["Y"] @ P
    z_coef = np.polyfit(kappa, ss.z, POLY_DEGREE)
    u_coef = np.polyfit(kappa, ss.u, POLY_DEGREE)
    return ChronosTerminalCBF(P, K, track, z_coef, u_coef, LEVEL, sol.status, ss)


# -- invariance check by randomly initialized NLPs ---------------------------------------------
@dataclass
class InvarianceReport:
    """Largest values found (<= 0: no counterexample) and the number of NLPs solved."""

    constraints: float
    inputs: float
    decrease: float
    solved: int
    failed: int
    worst_state: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """No counterexample *and* every row maximized by at least one solved NLP (a check
        whose NLPs all failed has checked nothing)."""
        values = (self.constraints, self.inputs, self.decrease)
        return (self.solved > 0 and all(np.isfinite(v) for v in values)
                and max(values) <= 1e-6)


def _maximize(objective, region, starts: np.ndarray, target: object) -> tuple[float, np.ndarray,
                                                                             int, int]:
    """``max objective(x)`` s.t. ``region(x) <= 0`` from every start (a generic NLP in the
    language, compiled for ``target``); returns the best value, its state and the counts
    of successful and failed solves."""
    ocp = OCP(name="chronos_invariance_check")
    x = ocp.variable("x", 6)
    ocp.le(region(x), 0.0, name="region")
    ocp.minimize(-objective(x))
    prob = compile(ocp, target)
    best, arg, ok, bad = -np.inf, starts[0], 0, 0
    for x0 in starts:
        sol = prob.solve({}, warm_start={"x": x0})
        if not sol.success:
            bad += 1
            continue
        ok += 1
        val = -float(sol.objective)
        if val > best:
            best, arg = val, np.asarray(sol.primal["x"], dtype=float).reshape(-1)
    return best, arg, ok, bad


def random_states_in(cbf: ChronosTerminalCBF, n: int, level: float, rng: np.random.Generator
                     ) -> np.ndarray:
    """``n`` random Frenet states with ``V <= level``: random ``s``, random direction and
    radius in the ellipsoid around ``z_ss(κ(s))``."""
    L = np.linalg.cholesky(np.linalg.inv(cbf.P))
    out = []
    for _ in range(n):
        s = rng.uniform(0.0, cbf.track.length)
        d = rng.standard_normal(5)
        d *= np.sqrt(level) * rng.uniform() ** 0.2 / np.linalg.norm(d)
        dz = L @ d
        zs, _ = cbf._parts(np.r_[s, np.zeros(5)])
        out.append(np.r_[s, dz - zs])
    return np.array(out)


def check_invariance(cbf: ChronosTerminalCBF, system: System | None = None, starts: int = 20,
                     seed: int = 0, target: object = "exact",
                     params: ChronosParams = TABLE_8_1) -> InvarianceReport:
    """The §8.4 check by randomly initialized NLPs (module docstring) for the PCBF model
    ``system`` (default: Euler Frenet model on ``cbf.track``)."""
    starts = as_count(starts, "check_invariance: starts", low=1)
    system = chronos_frenet(cbf.track, params=params) if system is None else system
    _, U = chronos_sets(params)
    rng = np.random.default_rng(seed)
    x1 = random_states_in(cbf, starts, 1.0, rng)
    x0 = random_states_in(cbf, starts, cbf.level, rng)
    counts = [0, 0]  # NLPs solved, failed

    def worst(rows, n_rows: int, region, starts_: np.ndarray) -> tuple[float, np.ndarray]:
        """The largest of ``rows(x)[r]`` over ``region(x) <= 0``, over all rows ``r``."""
        best = (-np.inf, starts_[0])
        for r in range(n_rows):
            v, arg, ok, bad = _maximize(lambda x, r=r: rows(x)[r], region, starts_, target)
            counts[0], counts[1] = counts[0] + ok, counts[1] + bad
            if ok == 0:                         # nothing solved: this row is unchecked
                v = np.inf
            best = max(best, (v, arg), key=lambda t: t[0])
        return best

    def v1(x: ca.SX) -> ca.SX:  # the 1-sublevel set {V <= 1}
        return cbf.V(x) - 1.0

    def input_rows(x: ca.SX) -> ca.SX:  # π_f(x) ∈ U as rows <= 0
        return ca.vertcat(cbf.policy(x) - ca.DM(U.ub), ca.DM(U.lb) - cbf.policy(x))

    def next_h(x: ca.SX) -> ca.SX:  # h_f(f(x, π_f(x)))
        return ca.vertcat(cbf(system(x, cbf.policy(x))))

    c_val, c_arg = worst(lambda x: constraint_values(x, params), 6, v1, x1)
    u_val, u_arg = worst(input_rows, 4, v1, x1)      # π_f ∈ U on the domain D_f = {V <= 1}
    d_val, d_arg = worst(next_h, 1, cbf, x0)
    solved, failed = counts
    return InvarianceReport(c_val, u_val, d_val, solved, failed,
                            {"constraints": c_arg.tolist(), "inputs": u_arg.tolist(),
                             "decrease": d_arg.tolist()})


# -- the PCBF (2.24) ---------------------------------------------------------------------------
@dataclass
class ChronosDesign:
    """Everything the §8.4 PCBF needs: the Euler Frenet model, ``X`` (corners (8.6),
    ``|μ| <= π/2``), ``U``, the terminal CBF, ``N = 50``, ``Δ_i = i·10⁻⁴``, ``α_f = 10``,
    and a box ``sample_box`` for sampling goal points."""

    track: Track
    system: System
    X: FunctionSet
    U: Box
    cbf: ChronosTerminalCBF
    N: int
    deltas: np.ndarray
    alpha_f: float
    sample_box: Box


def chronos_design(N: int = 50, delta_step: float = 1e-4, alpha_f: float = 10.0,
                   track: Track | None = None, params: ChronosParams = TABLE_8_1
                   ) -> ChronosDesign:
    """The §8.4 PCBF design on ``track`` (default: the SPEC oval)."""
    track = oval() if track is None else track
    N = as_count(N, "chronos_design: N", low=1)
    system = chronos_frenet(track, params=params)
    X, U = chronos_sets(params)
    cbf = chronos_terminal_cbf(track, params)
    deltas = as_scalar(delta_step, "chronos_design: delta_step", low=0.0) * np.arange(N)
    box = Box([0.0, -0.35, -0.8, 0.3, -0.4, -4.0],
              [track.length, 0.35, 0.8, 2.2, 0.4, 4.0], name="chronos_sample_box")
    return ChronosDesign(track, system, X, U, cbf, N, deltas, float(alpha_f), box)


def chronos_problems(target: str = "fast-sqp", N: int = 50, slack_norm: int = 1
                     ) -> PCBFProblems:
    """(2.24) and (7.8) of the §8.4 design compiled for sampling (Algorithm 7.6), as the
    sampler's ``"chronos"`` problem (:data:`balustrade.learn.sampler.PROBLEMS`)."""
    d = chronos_design(N=N)
    args = (d.system, d.X, d.U, d.cbf, d.N, d.deltas)
    slack, slack_cold = compile_pair(
        pcbf_slack_problem(*args, alpha_f=d.alpha_f, slack_norm=slack_norm), target)
    extended, extended_cold = compile_pair(extended_pcbf_problem(*args), target)
    return PCBFProblems(slack, extended, d.sample_box, 1.0, slack_cold, extended_cold)


def pcbf_states(design: ChronosDesign, n: int, seed: int = 0) -> np.ndarray:
    """``n`` test states for timing (2.24): random ``s``, lateral offset and heading up to
    the track edge, speed 0.5–2 m/s, small ``v_y`` and ``ω``."""
    rng = np.random.default_rng(seed)
    lo = np.array([0.0, -0.22, -0.4, 0.5, -0.1, -1.0])
    hi = np.array([design.track.length, 0.22, 0.4, 2.0, 0.1, 1.0])
    return lo + (hi - lo) * rng.uniform(size=(as_count(n, "pcbf_states: n", low=1), 6))


def time_pcbf(targets: tuple[str, ...] = ("exact", "fast-sqp", "structured-sqp",
                                          "long-horizon"),
              n_states: int = 5, design: ChronosDesign | None = None, seed: int = 0
              ) -> dict[str, dict]:
    """Wall time of one cold solve of the PCBF (2.24) (``N = 50``) per target on
    :func:`pcbf_states`: median, max, statuses and objectives (the problem is nonconvex:
    targets may stop in different local minima — compare the objectives). A target that
    refuses the problem is reported with the reason."""
    d = chronos_design() if design is None else design
    ocp = pcbf_slack_problem(d.system, d.X, d.U, d.cbf, d.N, d.deltas, alpha_f=d.alpha_f,
                             slack_norm=1)
    states = pcbf_states(d, n_states, seed)
    out: dict[str, dict] = {}
    for name in targets:
        try:
            prob = compile(ocp, name)
        except BalustradeError as exc:
            out[name] = {"refused": str(exc)}
            continue
        times, statuses, objectives = [], [], []
        for x in states:
            t0 = time.perf_counter()
            sol = prob.solve({"x0": x})
            times.append(time.perf_counter() - t0)
            statuses.append(str(sol.status))
            objectives.append(float(sol.objective) if sol.success else float("nan"))
        out[name] = {"median_s": float(np.median(times)), "max_s": float(np.max(times)),
                     "all_ok": all(s == "optimal" for s in statuses), "statuses": statuses,
                     "objectives": objectives}
    return out


__all__ = ["ChronosDesign", "ChronosTerminalCBF", "InvarianceReport", "SteadyStates",
           "check_invariance", "chronos_design", "chronos_problems", "chronos_terminal_cbf",
           "pcbf_states", "random_states_in", "steady_states", "terminal_cbf_sdp",
           "time_pcbf"]
