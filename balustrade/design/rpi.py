"""Offline design of ellipsoidal RPI error sets (Assumption 5.13, SPEC §1.11): solve the SDP
(5.14) of :mod:`balustrade.problems.rpi` on a synthesis target over a line search in ``λ``.

The formulation lives in ``problems/`` (language only); the solves live here.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from balustrade.backends import compile_synthesis
from balustrade.dsl.error_sets import ErrorSet, is_rpi
from balustrade.dsl.sets import Ellipsoid, Polytope, Set
from balustrade.errors import BalustradeError, EmptySetError
from balustrade.problems.rpi import rpi_sdp


def ellipsoidal_rpi(A: np.ndarray, B: np.ndarray, W: Set, X: Polytope, U: Polytope,
                    G: np.ndarray | None = None, lambdas: Sequence[float] | None = None,
                    target: object = "sdp", name: str = "E") -> ErrorSet:
    """Ellipsoidal RPI set and error feedback: :func:`rpi_sdp` compiled once and solved for
    each ``λ`` of the line search (default 19 values in ``(0, 1)``), keeping the best.

    Returns ``ErrorSet(Ellipsoid(E_P⁻¹), K = Y E_P⁻¹)`` with the objective, the chosen ``λ``,
    the solver status, the margin of :func:`~balustrade.dsl.error_sets.is_rpi`, whether that
    check is a proof (``info["rpi_proven"]``: ``False`` when ``W`` is not a polytope, where it
    only samples and warns; a singular ``A_K`` is checked exactly since session 15) and the
    solve time in ``info``. The best ``optimal`` solve is chosen; an ``optimal_inaccurate``
    one only when no full-accuracy solve passes, and any choice only when ``is_rpi`` confirms
    ``A_K E ⊕ G W ⊆ E`` (rejected ones in ``info["refused"]``; none → ``BalustradeError``);
    a miss within the solver's accuracy (:data:`RPI_REPAIR`) is repaired by inflating ``E``
    (``info["inflation"]``, 1 when not needed).
    ``target``: a synthesis target (preset ``"sdp"``)."""
    lambdas = list(lambdas) if lambdas is not None else list(np.linspace(0.05, 0.95, 19))
    for lv in lambdas:
        if not 0 < lv < 1:
            raise BalustradeError(f"ellipsoidal_rpi: lambdas: every λ must lie in (0, 1), "
                                  f"got {lv}")
    compiled = compile_synthesis(rpi_sdp(A, B, W, X, U, G), target)
    solved = []
    start = time.perf_counter()
    for lv in lambdas:
        sol = compiled.solve({"lambda": lv})
        if sol.ok:
            solved.append((sol, lv))
    elapsed = time.perf_counter() - start
    if not solved:
        raise BalustradeError("RPI SDP: no λ in the line search admits an ellipsoidal RPI set "
                              f"(tried {len(lambdas)} values); the system may not be "
                              "stabilizable against W")
    # full-accuracy solves first, each by objective; an "optimal_inaccurate" one only after
    # them, and none without the solver-independent check A_K E ⊕ G W ⊆ E (is_rpi): a set
    # that is not RPI would void every robust guarantee built on it (Theorem 5.15)
    solved.sort(key=lambda s: (s[0].status != "optimal", s[0].objective))
    A = np.asarray(A, dtype=float)
    B = np.asarray(B, dtype=float)
    refused = []
    for sol, lv in solved:
        error, check, scale = _verified(sol, A, B, W, G, name)
        if check.ok:
            error.info.update({"objective": sol.objective, "lambda": lv, "status": sol.status,
                               "rpi_margin": check.margin, "rpi_check": check.method,
                               "rpi_proven": check.proven,
                               "inflation": scale,
                               "solve_time": elapsed,
                               "method": "ellipsoidal SDP (SPEC §1.11)"})
            if refused:
                error.info["refused"] = refused
            _check_tightenings(error, W, X, U)
            return error
        refused.append({"lambda": lv, "status": sol.status, "rpi_margin": check.margin})
    raise BalustradeError("RPI SDP: no solution of the line search is RPI by the check "
                          f"A_K E ⊕ G W ⊆ E (is_rpi): {refused}")


def _check_tightenings(error: ErrorSet, W: Set, X: Polytope, U: Polytope) -> None:
    """The tube needs ``X ⊖ E`` and ``U ⊖ K E`` nonempty (SPEC §1.5, (5.15e–f)); the SDP
    of §1.11 only shrinks ``E`` relative to ``X``, ``U``, so a ``W`` too large for them
    returns an RPI set that empties them. Refused here, naming ``W``, ``X``/``U`` and the
    RPI set, instead of as an :class:`EmptySetError` of a later tightening."""
    for label, S, tighten in (("X", X, error.tighten_state), ("U", U, error.tighten_input)):
        try:
            tighten(S)
        except EmptySetError as exc:
            if label == "X":
                sup = np.array([error.E.support(a) for a in S.H])
            else:
                sup = np.array([error.E.support(error.K.T @ a) for a in S.H])
            j = int(np.argmax(sup / S.h))
            raise EmptySetError(
                f"ellipsoidal_rpi: the RPI set {error.E.name} for W ({W.name}) is too large "
                f"for {label} ({S.name}): {label} ⊖ {'K·' if label == 'U' else ''}"
                f"{error.E.name} is empty (row {j}: support {sup[j]:.4g} vs bound "
                f"{S.h[j]:.4g}); shrink W or enlarge {label}") from exc


#: largest miss of A_K E ⊕ G W ⊆ E (in units of c_E(e) = eᵀPe − 1) repaired by inflating E:
#: the SDP holds in E_P = P⁻¹ to the solver's tolerance, and inverting an ill-conditioned E_P
#: (cond ≈ 1e7 on the bicycle linearization) turns that into misses of ≈ 3e-6 in P
RPI_REPAIR = 1e-4


def _verified(sol: object, A: np.ndarray, B: np.ndarray, W: Set, G: np.ndarray | None,
              name: str) -> tuple[ErrorSet, object, float]:
    """``ErrorSet(Ellipsoid(E_P⁻¹), K = Y E_P⁻¹)`` of one solve of (5.14) with its
    :func:`is_rpi` check. A miss within :data:`RPI_REPAIR` is repaired by inflating ``E`` by
    ``s > 1`` (same ``K``): ``A_K(sE) ⊕ GW ⊆ sE`` iff ``A_K E ⊕ GW/s ⊆ E``, which holds for
    ``s`` large enough since ``A_K`` is contractive on ``E`` (λ < 1 in (5.14))."""
    Ev = 0.5 * (sol["E"] + sol["E"].T)
    P = np.linalg.inv(Ev)
    P = 0.5 * (P + P.T)
    K = sol["Y"] @ P
    A_cl = A + B @ K
    scale, check = 1.0, is_rpi(Ellipsoid(P, name=name), A_cl, W, G)
    for k in range(6):
        if check.ok or check.margin > RPI_REPAIR:
            break
        # the miss is measured on the set already inflated: compound, never step back
        scale *= 1.0 + 4.0 ** k * max(check.margin, 1e-9)
        check = is_rpi(Ellipsoid(P / scale ** 2, name=name), A_cl, W, G)
    return ErrorSet(Ellipsoid(P / scale ** 2, name=name), K, info={}), check, scale

__all__ = ["RPI_REPAIR", "ellipsoidal_rpi"]
