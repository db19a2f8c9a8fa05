"""Monte Carlo volumes of admissible sets (thesis §4.7, Table 4.1; issue #15 item 5).

The admissible set of a problem whose constraints are affine in the decision variables ``y``
and in the initial state ``x`` — e.g. (4.5) with homothetic tubes (SPEC §2.20) for fixed
vertices of ``Θ``, or the baseline PSF — is ``𝓕 = {x : ∃y, A y + C x + c (<=, ==) 0,
lb <= y <= ub}``. Its volume is estimated by sampling ``x`` uniformly in a box ``X`` and
deciding one feasibility LP per sample (:func:`feasibility_lp` builds the LP matrices once from
the OCP; :func:`balustrade.backends.lp_batch.feasible_many` solves the batch, changing only
the row bounds). ``vol 𝓕 ≈ vol X · k/S`` with a Wilson score interval for ``k/S``.

**Common random numbers.** :func:`admissible_volumes` decides *every* set on the *same*
samples, so an inclusion such as ``𝓕(Θ₀) ⊆ 𝓕(Θ₁₅₀) ⊆ 𝓕_f(Θ₁₅₀)`` (Theorems 4.7, 4.10) is
checked sample by sample (``nesting_violations``), and the differences of volumes have far
smaller variance than independent estimates. Undecided LPs (neither feasible nor infeasible
after a retry) are counted and reported, never counted as feasible in the estimate; the
intervals let them go either way (session 13, audit finding 4): the volume interval is
``[Wilson(k).lo, Wilson(k + u).hi]`` (``u`` undecided samples), and the growth interval of
:meth:`VolumeReport.growth` is taken at the worst completion of the undecided samples.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade._checks import check_instance
from balustrade.backends.lp_batch import (
    FEASIBLE,
    INFEASIBLE,
    UNDECIDED,
    BatchLP,
    feasible_many,
)
from balustrade.dsl import OCP
from balustrade.dsl.sets import Box
from balustrade.errors import BalustradeError, ShapeError

#: two-sided 95 % normal quantile (Wilson interval)
Z95 = 1.959963984540054


@dataclass(frozen=True)
class FeasibilityLP:
    """``{y : row_lb(x) <= A y <= row_ub(x), lb <= y <= ub}`` with row bounds affine in
    ``x``: ``row_ub(x) = ub0 − C x``, ``row_lb(x) = lb0 − C x`` (``lb0 = −inf`` on the
    inequality rows, ``= ub0`` on the equality rows)."""

    lp: BatchLP
    C: np.ndarray
    lb0: np.ndarray
    ub0: np.ndarray
    name: str = "F"

    @property
    def dim(self) -> int:
        return self.C.shape[1]

    def row_bounds(self, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        shift = np.atleast_2d(xs) @ self.C.T
        return self.lb0[None, :] - shift, self.ub0[None, :] - shift

    def feasible(self, xs: np.ndarray, progress: Callable[[int], None] | None = None,
                 time_limit: float | None = None) -> np.ndarray:
        """Outcome per row of ``xs`` (``1`` feasible, ``0`` infeasible, ``−1`` undecided;
        also undecided: an LP stopped by ``time_limit`` seconds)."""
        xs = np.atleast_2d(np.asarray(xs, dtype=float))
        if xs.shape[1] != self.dim:
            raise ShapeError(f"{self.name}.feasible: xs", f"rows of length {self.dim}",
                             xs.shape)
        lo, hi = self.row_bounds(xs)
        return feasible_many(self.lp, lo, hi, progress, time_limit)


#: seconds per LP when samples the compiled solver left undecided are re-checked by the
#: feasibility LP; one stopped by it stays undecided (counted apart in the estimate)
RECHECK_TIME_LIMIT = 60.0


def feasibility_lp(ocp: OCP, state: str = "x0", values: Mapping[str, object] | None = None,
                   name: str | None = None) -> FeasibilityLP:
    """The feasibility LP of ``ocp`` as a function of its parameter ``state`` (the cost is
    ignored; the other parameters are fixed to ``values``, default their declared values).
    Raises when a constraint is not affine in ``(y, state)`` jointly."""
    check_instance(ocp, OCP, "feasibility_lp: ocp")
    name = name or ocp.name
    if state not in ocp.parameters:
        raise BalustradeError(f"feasibility_lp: {ocp.name} has no parameter {state!r} "
                              f"(parameters: {sorted(ocp.parameters)})")
    values = dict(values or {})
    xsym = ca.vec(ocp.parameters[state].sym)
    others = [p for p in ocp.parameters.values() if p.name != state]
    y = ocp.decision_vector()
    exprs = {kind: ca.vertcat(ca.SX(0, 1), *[b.expr for b in ocp.blocks if b.kind == kind])
             for kind in ("le", "eq")}
    both = ca.vertcat(exprs["le"], exprs["eq"])
    for p in others:
        sym = ca.vec(p.sym)
        if not ca.depends_on(both, sym):
            continue                                   # cost-only parameters (u_p)
        value = values.get(p.name, p.default)
        if value is None:
            raise BalustradeError(f"feasibility_lp: parameter {p.name!r} of {ocp.name} enters "
                                  "the constraints and has no value: pass it in values")
        val = np.asarray(value, dtype=float)
        if val.size != sym.numel():
            raise ShapeError(f"feasibility_lp: values[{p.name!r}]", p.shape, val.shape)
        val = val.reshape(p.shape).ravel(order="F")
        exprs = {k: ca.substitute(e, sym, ca.DM(val)) for k, e in exprs.items()}
    yx = ca.vertcat(y, xsym)
    parts = {}
    for kind, e in exprs.items():
        if e.numel() and not ca.is_linear(e, yx):
            raise BalustradeError(f"feasibility_lp: the {kind!r} constraints of {ocp.name} "
                                  f"are not affine in the variables and {state!r}")
        f = ca.Function("f", [y, xsym], [ca.jacobian(e, y), ca.jacobian(e, xsym), e])
        A, C, c = f(np.zeros(y.numel()), np.zeros(xsym.numel()))
        parts[kind] = (np.array(A), np.array(C), np.array(c).ravel())
    (Al, Cl, cl), (Ae, Ce, ce) = parts["le"], parts["eq"]
    A = np.vstack([Al, Ae])
    C = np.vstack([Cl, Ce])
    ub0 = -np.concatenate([cl, ce])
    lb0 = np.concatenate([np.full(cl.size, -np.inf), -ce])
    lb, ub = ocp.bounds()
    return FeasibilityLP(BatchLP.build(A, lb, ub), C, lb0, ub0, name=name)


class CompiledFeasibility:
    """The same decision as :class:`FeasibilityLP` by solving the OCP itself, compiled once
    on ``target`` with ``state`` as a parameter (e.g. ``"fast-convex"``): ``optimal`` is
    feasible, ``infeasible`` infeasible, any other status undecided — and then decided by
    the LP path (:func:`feasibility_lp`), built on first need."""

    def __init__(self, ocp: OCP, target: object = "fast-convex", state: str = "x0",
                 values: Mapping[str, object] | None = None, name: str | None = None):
        from balustrade.backends import compile

        check_instance(ocp, OCP, "CompiledFeasibility: ocp")
        if state not in ocp.parameters:
            raise BalustradeError(f"CompiledFeasibility: {ocp.name} has no parameter "
                                  f"{state!r} (parameters: {sorted(ocp.parameters)})")
        self.ocp, self.state, self.name = ocp, state, name or ocp.name
        given, rows = dict(values or {}), ocp.constraint_vector()
        self.values = {}
        for p in ocp.parameters.values():
            if p.name == state:
                continue
            value = given.get(p.name, p.default)
            if value is None and ca.depends_on(rows, ca.vec(p.sym)):
                raise BalustradeError(f"CompiledFeasibility: parameter {p.name!r} of "
                                      f"{ocp.name} enters the constraints and has no value: "
                                      "pass it in values")
            self.values[p.name] = np.zeros(p.shape) if value is None else value  # cost only
        self.dim = ocp.parameters[state].sym.numel()
        self.compiled = compile(ocp, target)
        self._lp: FeasibilityLP | None = None

    def feasible(self, xs: np.ndarray, progress: Callable[[int], None] | None = None
                 ) -> np.ndarray:
        xs = np.atleast_2d(np.asarray(xs, dtype=float))
        if xs.shape[1] != self.dim:
            raise ShapeError(f"{self.name}.feasible: xs", f"rows of length {self.dim}",
                             xs.shape)
        out = np.full(xs.shape[0], UNDECIDED, dtype=np.int8)
        for s, x in enumerate(xs):
            status = str(self.compiled.solve({**self.values, self.state: x}).status)
            out[s] = {"optimal": FEASIBLE, "infeasible": INFEASIBLE}.get(status, UNDECIDED)
            if progress is not None:
                progress(s)
        if np.any(out == UNDECIDED):
            if self._lp is None:
                self._lp = feasibility_lp(self.ocp, self.state, self.values, self.name)
            todo = np.flatnonzero(out == UNDECIDED)
            recheck = None if progress is None else (
                lambda k: progress(int(todo[k])))   # keeps the progress line alive
            out[todo] = self._lp.feasible(xs[todo], recheck, RECHECK_TIME_LIMIT)
        return out


# -- estimates ---------------------------------------------------------------------------------
def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion ``k/n`` (default 95 %)."""
    if n <= 0:
        raise BalustradeError(f"wilson_interval: n must be positive, got {n}")
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    lo = 0.0 if k == 0 else max(0.0, centre - half)         # exact ends (no rounding)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return float(lo), float(hi)


def volume_interval(feasible: int, undecided: int, n: int, z: float = Z95
                    ) -> tuple[float, float]:
    """95 % interval of the feasible fraction when ``undecided`` of the ``n`` samples could
    be either: ``[Wilson(feasible, n).lo, Wilson(feasible + undecided, n).hi]`` (each end
    at the completion of the undecided samples that is worst for it)."""
    return (wilson_interval(feasible, n, z)[0], wilson_interval(feasible + undecided, n, z)[1])


#: two-sided quantile of level 1 − 0.05/2 (Bonferroni over the two proportions of
#: :func:`paired_growth_interval`, so that both hold together with probability >= 95 %)
Z975 = 2.241402727604947


def paired_growth_interval(small: np.ndarray, large: np.ndarray, z: float = Z975
                           ) -> tuple[float, float, dict]:
    """95 % interval of ``vol L / vol S − 1`` from paired outcomes (FEASIBLE / INFEASIBLE /
    UNDECIDED per sample, the same samples for both sets).

    Among the ``m`` samples in ``S ∪ L`` let ``n_L`` be in ``L`` only and ``n_S`` in ``S``
    only. Conditioned on ``m`` these are multinomial with probabilities ``q_L, q_S`` and
    ``vol L / vol S = (1 − q_S)/(1 − q_L)``; Wilson intervals for ``q_L`` and ``q_S`` at
    level 97.5 % each (both hold with probability >= 95 %) give
    ``[(1 − q_S.hi)/(1 − q_L.lo), (1 − q_S.lo)/(1 − q_L.hi)] − 1``. So 0 differing samples of
    200 give about ``[−2.5 %, +2.5 %]``, not ``[0, 0]``. The lower end counts every
    undecided sample of ``S`` as in ``S`` and of ``L`` as not in ``L`` (the completion that
    lowers it most), the upper end the reverse. Also returns the counts ``only_large``,
    ``only_small``, ``union`` with undecided samples counted as infeasible (as the
    estimates)."""
    small, large = np.asarray(small), np.asarray(large)
    nan = float("nan")

    def ends(a: np.ndarray, b: np.ndarray) -> tuple[int, int, int]:
        return int(np.sum(b & ~a)), int(np.sum(a & ~b)), int(np.sum(a | b))

    # lower end: S as large as the data allow, L as small
    nL, nS, m = ends(small != INFEASIBLE, large == FEASIBLE)
    lo = nan if m == 0 else ((1 - wilson_interval(nS, m, z)[1])
                             / (1 - wilson_interval(nL, m, z)[0]) - 1)
    # upper end: S as small, L as large
    nL2, nS2, m2 = ends(small == FEASIBLE, large != INFEASIBLE)
    if m2 == 0:
        hi = nan
    else:
        q_hi = wilson_interval(nL2, m2, z)[1]
        hi = float("inf") if q_hi >= 1 else (1 - wilson_interval(nS2, m2, z)[0]) / (1 - q_hi) - 1
    nL0, nS0, m0 = ends(small == FEASIBLE, large == FEASIBLE)
    counts = {"only_large": nL0, "only_small": nS0, "union": m0}
    return float(lo), float(hi), counts


@dataclass(frozen=True)
class VolumeEstimate:
    """``volume = box_volume · feasible/samples`` and its 95 % interval
    ``box_volume · [Wilson(feasible).lo, Wilson(feasible + undecided).hi]``
    (:func:`volume_interval`): undecided samples are excluded from ``feasible`` (the
    estimate) and listed in ``undecided``; the interval allows each to be either."""

    name: str
    samples: int
    feasible: int
    undecided: int
    box_volume: float
    interval: tuple[float, float]
    seconds: float

    @property
    def fraction(self) -> float:
        return self.feasible / self.samples

    @property
    def volume(self) -> float:
        return self.box_volume * self.fraction

    def as_dict(self) -> dict:
        return {"volume": self.volume, "ci95": list(self.interval), "fraction": self.fraction,
                "samples": self.samples, "feasible": self.feasible,
                "undecided": self.undecided, "seconds": self.seconds}


@dataclass
class VolumeReport:
    """All estimates on the same samples, the outcome matrix (sets × samples) and, for the
    declared order, the samples in set ``i`` but not in set ``i + 1``."""

    box_volume: float
    samples: np.ndarray
    estimates: dict[str, VolumeEstimate]
    outcomes: dict[str, np.ndarray]
    order: tuple[str, ...] = ()
    nesting_violations: dict[str, int] = field(default_factory=dict)

    def growth(self, small: str, large: str) -> dict:
        """Relative growth ``vol large / vol small − 1`` on the paired samples (common
        random numbers) and a 95 % interval (:func:`paired_growth_interval`): from the
        samples in one set but not the other, so that 0 differing samples still give an
        interval of positive width, and with the undecided samples of either set at the
        completion that is worst for each end. The point estimate counts undecided samples
        as infeasible, as :class:`VolumeEstimate` does."""
        oa, ob = self.outcomes[small], self.outcomes[large]
        a, b = oa == FEASIBLE, ob == FEASIBLE
        lo, hi, counts = paired_growth_interval(oa, ob)
        growth = float(b.sum() / a.sum() - 1) if a.sum() else float("nan")
        return {"growth": growth, "ci95": [lo, hi], **counts}

    def as_dict(self) -> dict:
        return {"box_volume": self.box_volume, "samples": int(self.samples.shape[0]),
                "sets": {k: e.as_dict() for k, e in self.estimates.items()},
                "order": list(self.order), "nesting_violations": self.nesting_violations}


def box_samples(X: Box, count: int, seed: int | np.random.Generator = 0) -> np.ndarray:
    """``count`` points uniform in the bounded box ``X`` (rows)."""
    check_instance(X, Box, "box_samples: X")
    if not X.is_bounded():
        raise BalustradeError("box_samples: X must be a bounded box")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    return rng.uniform(X.lb, X.ub, size=(int(count), X.dim))


def admissible_volumes(sets: Mapping[str, FeasibilityLP], X: Box, samples: int | np.ndarray,
                       seed: int = 0, order: Sequence[str] = (),
                       progress: Callable[[str], None] | None = None) -> VolumeReport:
    """Monte Carlo volume of every admissible set in ``sets`` on the same uniform samples of
    ``X`` (or on the given sample array); ``order`` names sets expected to be nested
    (smallest first) and counts the samples that break it. ``progress`` receives a status
    line about every second (:func:`print_progress` writes it to stderr)."""
    check_instance(X, Box, "admissible_volumes: X")
    xs = (np.atleast_2d(np.asarray(samples, dtype=float)) if np.ndim(samples)
          else box_samples(X, int(samples), seed))
    if xs.shape[1] != X.dim:
        raise ShapeError("admissible_volumes: samples", f"rows of length {X.dim}", xs.shape)
    unknown = [k for k in order if k not in sets]
    if unknown:
        raise BalustradeError(f"admissible_volumes: order names unknown sets {unknown}")
    box_volume = float(np.prod(X.ub - X.lb))
    estimates, outcomes = {}, {}
    for name, lp in sets.items():
        start = time.perf_counter()
        ticker = _Ticker(name, xs.shape[0], progress, start)
        out = lp.feasible(xs, ticker)
        ticker.done(out)
        k, u = int(np.sum(out == FEASIBLE)), int(np.sum(out == UNDECIDED))
        estimates[name] = VolumeEstimate(name, xs.shape[0], k, u, box_volume,
                                         tuple(box_volume * p for p in
                                               volume_interval(k, u, xs.shape[0])),
                                         time.perf_counter() - start)
        outcomes[name] = out
    violations = {f"{a} ⊆ {b}": int(np.sum((outcomes[a] == FEASIBLE)
                                            & (outcomes[b] != FEASIBLE)))
                  for a, b in zip(order, order[1:])}
    return VolumeReport(box_volume, xs, estimates, outcomes, tuple(order), violations)


class _Ticker:
    def __init__(self, name: str, total: int, sink: Callable[[str], None] | None,
                 start: float):
        self.name, self.total, self.sink, self.start = name, total, sink, start
        self.last = start

    def __call__(self, s: int) -> None:
        now = time.perf_counter()
        if self.sink is not None and now - self.last >= 1.0:
            self.last = now
            rate = (now - self.start) / (s + 1)
            self.sink(f"vol {self.name}: {s + 1}/{self.total} samples, "
                      f"{1e3 * rate:.2f} ms/LP, ~{rate * (self.total - s - 1):.0f} s left")

    def done(self, out: np.ndarray) -> None:
        if self.sink is not None:
            secs = time.perf_counter() - self.start
            self.sink(f"vol {self.name}: {self.total}/{self.total} samples, "
                      f"{int(np.sum(out == FEASIBLE))} feasible, {secs:.1f} s\n")


def print_progress(line: str) -> None:
    """A progress sink for :func:`admissible_volumes`: one overwritten stderr line."""
    sys.stderr.write("\r" + line.ljust(78) if not line.endswith("\n") else "\r" + line)
    sys.stderr.flush()


__all__ = ["CompiledFeasibility", "FeasibilityLP", "VolumeEstimate", "VolumeReport",
           "admissible_volumes", "box_samples", "feasibility_lp",
           "paired_growth_interval", "print_progress", "volume_interval", "wilson_interval"]
