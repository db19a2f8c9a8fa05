"""Issue #12 "No wrong answers": the three LMI forms give one optimum, and no level is below
what its own controller attains.

Every synthesis of Chapter 3 that takes ``lmi=`` is solved in banded coordinates (the default,
which re-solves outside them when the banded solve is not ok), in the chordal split, as one
cone and in the lifted form (the 𝒪 term by its LQ definition, problems/regret/lifting.py),
for random LTV systems × W ∈ {I, 𝒪, a random PSD weight} × constraints (3.41) on/off:

* the four levels agree to 1e-6 relative;
* each level is checked against a computation that does not use the SDP solver
  (:mod:`balustrade.problems.regret.verify`): for the energy-bound and adversarial problems the
  SDP's own value (``info["sdp_level"]``) must not be below the exact worst-case level of the
  returned controller, recomputed here; for the pointwise problems the level must not be below
  a certified lower bound (multi-start ascent with other starts than the synthesis' own).

The named case is the system of ``/work/shared/repro/regret_forms_disagree.py`` (rocket,
T = 10), where the banded (3.32) with W = 𝒪 ended "optimal_inaccurate" at 0.2393 (optimum
0.17983, its controller ≥ 0.1998) and was accepted by ``res.ok``.
"""

import numpy as np
import pytest

from balustrade.backends import resolve_target
from balustrade.control.regret_synthesis import (
    adversarial_regret,
    dynamic_regret,
    generalized_regret,
    hinf,
    pointwise_dynamic_regret,
    pointwise_regret,
    zero_x0_regret,
)
from balustrade.problems.regret import LTVSystem, StateInputConstraints, build_operators
from balustrade.problems.regret.verify import (
    adversarial_level,
    generalized_level_energy,
    hinf_level,
    pointwise_regret_lower_bound,
    worst_case_regret_energy,
    zero_x0_level,
)

FORMS = ("banded", "split", "single", "lifted")   # lifted: the 𝒪 term by its LQ definition
REL = 1e-6          # forms agree to this (the requirement)
TOL = 1e-6          # solver tolerance allowed below a certificate (relative)
# Clarabel's default gap tolerance is 1e-8 absolute + 1e-8 relative on its scaled problem; on
# levels of order 1e-3 with the 𝒪 weight that is ≈ 1e-6–1e-5 relative on the level, so the
# 1e-6 comparison is made at tighter tolerances (where the banded form of the stiff systems
# below ends "optimal_inaccurate" and must be re-solved by the fallback).
TIGHT = {"tol_gap_abs": 1e-9, "tol_gap_rel": 1e-9, "tol_feas": 1e-9}

# /work/shared/repro/regret_rocket10.json: a 6-state planar rocket linearization, T = 10,
# Q = R = E = I, x₀ = (1, 1, 0, 0, 0, 0), P = diag(400, 400, 400, 100, 100, 100), ω = T/λ_min(P)
ROCKET10_A = [[1.0, 0.0, -0.04905, 0.1, 0.0, -0.001635], [0.0, 1.0, 0.0, 0.0, 0.1, 0.0],
              [0.0, 0.0, 1.0, 0.0, 0.0, 0.1], [0.0, 0.0, -0.981, 1.0, 0.0, -0.04905],
              [0.0, 0.0, 0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]]
ROCKET10_B = [[0.0, -0.04864901625], [0.005, 0.0], [0.0, -0.04905], [0.0, -0.96496065],
              [0.1, 0.0], [0.0, -0.981]]


def random_case(seed: int, n: int = 2, m: int = 1, T: int = 5, stiff: bool = False):
    """A random LTV system (E_k invertible, time-varying Q/R), x₀, ω, P and a PSD weight.

    ``stiff``: near-integrators with weak inputs (like the rocket: cond 𝒪 in the hundreds, the
    case where the banded congruence for the 𝒪 weight is ill-conditioned)."""
    rng = np.random.default_rng(seed)
    if stiff:
        A0 = np.eye(n) + 0.1 * np.triu(rng.standard_normal((n, n)), 1)
        A = [A0 + 0.02 * rng.standard_normal((n, n)) for _ in range(T)]
        B = [0.1 * rng.standard_normal((n, m)) for _ in range(T)]
    else:
        A = [0.8 * rng.standard_normal((n, n)) for _ in range(T)]
        B = [rng.standard_normal((n, m)) for _ in range(T)]
    E = [np.eye(n) + 0.3 * rng.standard_normal((n, n)) for _ in range(T)]
    Q = [np.diag(rng.uniform(0.5, 2.0, n)) for _ in range(T + 1)]
    R = [np.diag(rng.uniform(0.5, 2.0, m)) for _ in range(T + 1)]
    ops = build_operators(LTVSystem.create(A, B, T, E=E, Q=Q, R=R))
    x0 = rng.standard_normal(n)
    Lp = rng.standard_normal((n, n))
    P = Lp @ Lp.T + n * np.eye(n)
    if stiff:
        P = P * 50.0
    omega = T / float(np.min(np.linalg.eigvalsh(P)))
    Rw = rng.standard_normal((ops.nd, ops.nd))
    Wr = Rw @ Rw.T / ops.nd + 0.5 * np.eye(ops.nd)
    box = np.vstack([np.eye(n), -np.eye(n)])
    cons = StateInputConstraints.from_halfspaces(box, np.full(2 * n, 6.0),
                                                 np.vstack([np.eye(m), -np.eye(m)]),
                                                 np.full(2 * m, 8.0))
    return ops, x0, omega, P, Wr, cons


def weight(ops, W):
    return {"I": np.eye(ops.nd), "O": ops.O}.get(W, W) if isinstance(W, str) else W


# (label, synthesis(ops, x0, ω, P, W, cons, lmi), certificate kind, uses W)
def _syntheses():
    kw = {"target": resolve_target("sdp", options=TIGHT)}

    def gen(ops, x0, om, P, W, c, f):
        return generalized_regret(ops, x0, om, W, constraints=c, lmi=f, **kw)

    def pw(ops, x0, om, P, W, c, f):
        return pointwise_regret(ops, x0, P, W, constraints=c, lmi=f, **kw)

    def zx(ops, x0, om, P, W, c, f):
        return zero_x0_regret(ops, W, constraints=c, constraint_P=P, lmi=f, **kw)

    def zxa(ops, x0, om, P, W, c, f):
        return zero_x0_regret(ops, W, adversarial_x0=True, constraints=c, constraint_P=P,
                              lmi=f, **kw)

    def dr(ops, x0, om, P, W, c, f):
        return dynamic_regret(ops, x0, om, constraints=c, lmi=f, **kw)

    def adv(ops, x0, om, P, W, c, f):
        return adversarial_regret(ops, constraints=c, constraint_P=P, lmi=f, **kw)

    def pdr(ops, x0, om, P, W, c, f):
        return pointwise_dynamic_regret(ops, x0, P, constraints=c, lmi=f, **kw)

    def hi(ops, x0, om, P, W, c, f):
        return hinf(ops, x0=x0, constraints=c, constraint_P=P, lmi=f, **kw)

    return {"generalized (3.28)": (gen, True), "pointwise (3.32)": (pw, True),
            "zero-x0 (3.30)": (zx, True), "adversarial-x0 (3.30)": (zxa, True),
            "dynamic (3.19)": (dr, False), "adversarial (3.24)": (adv, False),
            "pointwise dynamic (3.34)": (pdr, False), "SH-inf": (hi, False)}


SYNTHESES = _syntheses()


def independent_check(label, res, ops, x0, omega, P, Wm, seed):
    """The level against a solver-free computation on the returned Φ_u (module docstring)."""
    Pu = res.Phi_u
    sdp = res.info["sdp_level"]
    if label.startswith("pointwise"):
        W = Wm if label == "pointwise (3.32)" else None
        lb = pointwise_regret_lower_bound(ops, Pu, x0, P, W=W, starts=30, seed=seed + 7).value
        assert res.level >= lb * (1 - TOL), (label, res.level, lb)
        return lb
    exact = {
        "generalized (3.28)": lambda: generalized_level_energy(ops, Pu, x0, omega, Wm),
        "zero-x0 (3.30)": lambda: zero_x0_level(ops, Pu, Wm),
        "adversarial-x0 (3.30)": lambda: zero_x0_level(ops, Pu, Wm, adversarial_x0=True),
        "dynamic (3.19)": lambda: worst_case_regret_energy(ops, Pu, x0, omega).upper,
        "adversarial (3.24)": lambda: adversarial_level(ops, Pu),
        "SH-inf": lambda: hinf_level(ops, Pu),
    }[label]()
    assert sdp >= exact * (1 - TOL), (label, sdp, exact)        # the SDP bound is valid
    assert res.level == pytest.approx(exact, rel=1e-8)           # and the reported level exact
    return exact


def check_forms(label, ops, x0, omega, P, W, cons, seed):
    make, uses_w = SYNTHESES[label]
    Wm = weight(ops, W)
    results = {f: make(ops, x0, omega, P, W, cons, f) for f in FORMS}
    for f, res in results.items():
        assert res.ok, (label, f, res.status, res.info)
        independent_check(label, res, ops, x0, omega, P, Wm, seed)
    ref = results["single"].level
    for f in ("banded", "split", "lifted"):
        assert results[f].level == pytest.approx(ref, rel=REL, abs=1e-10), (
            label, f, results[f].level, ref, results[f].info)
    return results


CASES = [  # (seed, n, T, stiff, constraints): default run; the exhaustive sweep is slow
    (0, 2, 4, False, False), (1, 2, 5, False, True), (2, 3, 6, True, False),
    (3, 3, 5, True, True),
]


@pytest.mark.parametrize("seed,n,T,stiff,constrained", CASES)
@pytest.mark.parametrize("W", ["I", "O", "random"])
@pytest.mark.parametrize("label", [k for k, (_, w) in SYNTHESES.items() if w])
def test_weighted_syntheses_agree_in_all_forms(label, W, seed, n, T, stiff, constrained):
    ops, x0, omega, P, Wr, cons = random_case(seed, n=n, T=T, stiff=stiff)
    check_forms(label, ops, x0, omega, P, Wr if W == "random" else W,
                cons if constrained else None, seed)


@pytest.mark.parametrize("seed,n,T,stiff,constrained", CASES)
@pytest.mark.parametrize("label", [k for k, (_, w) in SYNTHESES.items() if not w])
def test_unweighted_syntheses_agree_in_all_forms(label, seed, n, T, stiff, constrained):
    ops, x0, omega, P, _, cons = random_case(seed, n=n, T=T, stiff=stiff)
    check_forms(label, ops, x0, omega, P, "I", cons if constrained else None, seed)


# problems whose 𝒪 term lmi="lifted" states through the LQ definition of 𝒪 and solves directly
# on these systems (problems/regret/lifting.py); (3.32) is lifted too but not always solved
# directly (its attempt is re-solved like a whitened one, docs/regret.md)
LIFTED_DIRECT = ("generalized (3.28)", "zero-x0 (3.30)")


@pytest.mark.parametrize("seed,n,T,stiff,constrained", CASES)
@pytest.mark.parametrize("label", LIFTED_DIRECT)
def test_competitive_ratio_is_solved_in_lifted_coordinates(label, seed, n, T, stiff,
                                                          constrained):
    """W = 𝒪, lmi="lifted": the 𝒪 term is lifted (no whitening of 𝒪) and the LMI solved to
    full accuracy without a re-solve, at the optimum of the split form (1e-6)."""
    from balustrade.backends.synthesis_structured import LIFTED_ROUTE

    ops, x0, omega, P, _, cons = random_case(seed, n=n, T=T, stiff=stiff)
    make = SYNTHESES[label][0]
    c = cons if constrained else None
    res = make(ops, x0, omega, P, "O", c, "lifted")
    assert res.ok and res.info["lmi"] == "banded", res.info
    assert res.info["banded_route"] == LIFTED_ROUTE and not res.info.get("banded_fallback")
    independent_check(label, res, ops, x0, omega, P, ops.O, seed)
    ref = make(ops, x0, omega, P, "O", c, "split")
    assert res.level == pytest.approx(ref.level, rel=REL, abs=1e-10)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(4, 12))
@pytest.mark.parametrize("label", list(SYNTHESES))
def test_exhaustive_sweep_of_forms(label, seed):
    rng = np.random.default_rng(100 + seed)
    n, m, T = int(rng.integers(1, 4)), int(rng.integers(1, 3)), int(rng.integers(2, 9))
    ops, x0, omega, P, Wr, cons = random_case(seed, n=n, m=m, T=T, stiff=seed % 2 == 1)
    weights = ["I", "O", Wr] if SYNTHESES[label][1] else ["I"]
    for W in weights:
        for constrained in (False, True):
            check_forms(label, ops, x0, omega, P, W, cons if constrained else None, seed)


def rocket10():
    ops = build_operators(LTVSystem.create(np.array(ROCKET10_A), np.array(ROCKET10_B), 10))
    P = np.diag([400.0, 400.0, 400.0, 100.0, 100.0, 100.0])
    return ops, np.array([1.0, 1.0, 0, 0, 0, 0]), P, 10 / 100.0


# optima of the rocket case by the split and the single cone, which agree to 2e-7 (and, for
# (3.28), with the exact level of their controllers): the reference for the default form
ROCKET10_PW_O = 0.1798315
ROCKET10_GEN_O = 0.5834274


def test_rocket10_pointwise_competitive_ratio_is_not_accepted_off_the_optimum():
    """The issue's case: (3.32) with W = 𝒪. The default (banded) answer must be the optimum,
    ok, and its controller must attain its level (certified lower bound) but not more."""
    ops, x0, P, _ = rocket10()
    res = pointwise_regret(ops, x0, P, W="O")
    assert res.ok
    assert res.level == pytest.approx(ROCKET10_PW_O, rel=2e-6)
    lb = pointwise_regret_lower_bound(ops, res.Phi_u, x0, P, W=ops.O, seed=3).value
    assert res.level * (1 - 1e-5) <= lb <= res.level * (1 + TOL)
    # the banded attempt is recorded, not silently dropped
    assert res.info["lmi"] == "split" and "banded solve ended" in res.info["banded_fallback"]


def test_rocket10_energy_competitive_ratio_level_is_its_controllers():
    """(3.28) with W = 𝒪: the default level is its controller's exact level and the optimum."""
    ops, x0, _, omega = rocket10()
    res = generalized_regret(ops, x0, omega, W="O")
    assert res.ok
    exact = generalized_level_energy(ops, res.Phi_u, x0, omega, ops.O)
    assert res.level == pytest.approx(exact, rel=1e-8)
    assert res.info["sdp_level"] >= exact * (1 - TOL)
    assert res.level == pytest.approx(ROCKET10_GEN_O, rel=REL)
    # the same directly in the lifted form (no whitening of 𝒪, no re-solve)
    lifted = generalized_regret(ops, x0, omega, W="O", lmi="lifted")
    assert lifted.ok and not lifted.info.get("banded_fallback")
    assert lifted.info["banded_route"].startswith("lifted")
    assert lifted.level == pytest.approx(ROCKET10_GEN_O, rel=REL)


@pytest.mark.slow
def test_rocket10_all_forms():
    ops, x0, P, omega = rocket10()
    for W in ("I", "O"):
        check_forms("pointwise (3.32)", ops, x0, omega, P, W, None, 0)
        check_forms("generalized (3.28)", ops, x0, omega, P, W, None, 0)


def test_rocket8_scrw_level_is_not_below_what_its_controller_attains():
    """Rocket of Section 3.8 at T = 8 with (3.41), SCRW ((3.32), W = 𝒪): the banded solve ends
    "optimal" at 0.0104890, but its controller attains ≥ 0.0104892 (certified lower bound) and
    the optimum (split) is 0.0104891. The certificate must catch it and the re-solve fix it."""
    from balustrade.models.rocket import RocketRegretSetup
    from balustrade.reproduce.rocket_regret import synthesis_makers

    setup = RocketRegretSetup(T=8)
    makers, ops, _ = synthesis_makers(setup)
    res = makers["SCRW"]()
    assert res.ok
    lb = pointwise_regret_lower_bound(ops, res.Phi_u, setup.x0, setup.P, W=ops.O, starts=30,
                                      seed=5).value
    assert lb <= res.level * (1 + TOL)
    assert res.level == pytest.approx(0.0104891, rel=2e-5)
