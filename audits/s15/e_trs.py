"""Audit E: maximize_quadratic_on_ball (problems/regret/verify.py) vs an own SDP (cvxpy +
Clarabel) of max w'Aw + 2b'w + c, ||w||^2 <= omega:  min t  s.t. [[nu I - A, -b], [-b', t - c - nu omega]] >= 0,
nu >= 0 (S-lemma, exact). Checks: value attained by a feasible w, value <= SDP <= upper, gap.
Cases: random indefinite, A < 0 interior/boundary, exact hard case (b orthogonal to the top
eigenspace, nu = alpha_max exactly), near-hard (beta_top = 1e-6 .. 1e-15), repeated top
eigenvalue, alpha_max = 0 exactly, tiny/huge scale."""
import cvxpy as cp
import numpy as np

from balustrade.problems.regret.verify import maximize_quadratic_on_ball


def sdp(A, b, c, om):
    n = len(b); nu = cp.Variable(); t = cp.Variable()
    M = cp.bmat([[nu * np.eye(n) - A, -b.reshape(-1, 1)], [-b.reshape(1, -1), cp.reshape(t - c - nu * om, (1, 1))]])
    pr = cp.Problem(cp.Minimize(t), [0.5 * (M + M.T) >> 0, nu >= 0])
    pr.solve(solver="CLARABEL")
    return t.value, pr.status

rng = np.random.default_rng(0)
cases = []
for i in range(40):
    n = rng.integers(2, 7)
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    kind = ["random", "negdef", "hard", "near", "repeated", "zero_top", "scaled"][i % 7]
    al = np.sort(rng.normal(size=n))
    if kind == "negdef": al = -np.abs(al) - 0.1
    if kind == "repeated": al[-2] = al[-1]
    if kind == "zero_top": al = al - al[-1]
    beta = rng.normal(size=n) * rng.choice([0.1, 1, 10])
    if kind in ("hard", "repeated", "zero_top"): beta[-1] = 0.0; beta[-2] *= (kind != "repeated")
    if kind == "near": beta[-1] = 10.0 ** -rng.integers(6, 16)
    sc = 10.0 ** rng.integers(-4, 5) if kind == "scaled" else 1.0
    A = sc * Q @ np.diag(al) @ Q.T; A = 0.5 * (A + A.T); b = sc * Q @ beta
    om = float(rng.choice([0.01, 1.0, 100.0]))
    cases.append((kind, A, b, float(rng.normal()), om))
bad = 0
for kind, A, b, c, om in cases:
    r = maximize_quadratic_on_ball(A, b, c, om)
    val_w = float(r.w @ A @ r.w + 2 * b @ r.w + c)
    feas = float(r.w @ r.w) / om - 1
    s, st = sdp(A, b, c, om)
    scale = 1 + abs(s)
    flags = []
    if feas > 1e-9: flags.append(f"w outside ball {feas:.1e}")
    if abs(val_w - r.value) > 1e-9 * (1 + abs(val_w)): flags.append("value not attained")
    if r.value > s + 1e-7 * scale: flags.append(f"value above SDP {r.value - s:.1e}")
    if r.upper < s - 1e-7 * scale: flags.append(f"upper below SDP {r.upper - s:.1e}")
    if r.upper - r.value > 1e-7 * scale: flags.append(f"gap {r.upper - r.value:.1e}")
    if r.value < r.upper - 1e-6 * scale: pass
    bad += bool(flags)
    print(f"{kind:9s} n={len(b)} om={om:6.2f} val={r.value: .8e} sdp={s: .8e} ({st}) upper={r.upper: .8e} hard={r.hard_case} nu={r.nu:.3e} {flags}")
print("flagged", bad, "of", len(cases))
