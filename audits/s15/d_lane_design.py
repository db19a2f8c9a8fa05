"""Audit D: independent checks of the §8.2 bicycle design (converging config, N=20, Δ step 1e-3).
Own numpy model, own tightening, own sampling and own multi-start NLP (casadi Opti, not the DSL)."""
import time

import casadi as ca
import numpy as np

from balustrade.examples.bicycle import bicycle_design
from balustrade.models.bicycle import TS, WHEELBASE

DEG = np.pi / 180
t0 = time.time()
d = bicycle_design(N=20, delta_step=1e-3)
P, K = d.error.E.P, d.error.K
Ep = np.linalg.inv(P)
print("lambda", d.error.info["lambda"], "semi-axes", np.sqrt(np.diag(Ep)))
print("domain", d.error.info["domain"]["lb"], d.error.info["domain"]["ub"])

def f_np(x, u, w):
    x = np.atleast_2d(x); u = np.atleast_2d(u); w = np.atleast_1d(w).reshape(-1)
    py, psi, v, de = x.T
    return np.column_stack([py + TS * v * np.sin(psi), psi + TS * v / WHEELBASE * np.tan(de) + w,
                            v + TS * u[:, 1], de + u[:, 0]])

# 1. own X ⊖ E, U ⊖ KE from support functions (box rows)
Xlb = np.array([-0.2, -35 * DEG, 0.5, -35 * DEG]); Xub = -Xlb.copy(); Xub[2] = 1.3
Ulb = np.array([-17.5 * DEG, -2.0]); Uub = -Ulb
sx = np.sqrt(np.diag(Ep)); su = np.sqrt(np.diag(K @ Ep @ K.T))
XE, UE = d.X_E, d.U_E
own_x = np.r_[Xub - sx, -(Xlb + sx)]
own_u = np.r_[Uub - su, -(Ulb + su)]
# match rows by H
def rowcmp(S, lb, ub, s):
    err = 0.0
    for a, b in zip(S.H, S.h):
        j = int(np.argmax(np.abs(a))); sgn = np.sign(a[j]); a_n = np.linalg.norm(a)
        own = (ub[j] - s[j]) if sgn > 0 else (-(lb[j] + s[j]))
        err = max(err, abs(b / a_n - own))
    return err
print("tightening X_E max row err", rowcmp(XE, Xlb, Xub, sx), "U_E", rowcmp(UE, Ulb, Uub, su))

# 2. Jacobian interval soundness: dense sampling of D, a_k within intervals; and tightness
ldi = d.ldi
lb, ub = ldi.domain.lb.copy(), ldi.domain.ub.copy()
rng = np.random.default_rng(7)
n = 400000
S = rng.uniform(lb[1:], ub[1:], (n, 3))
# include corners/edges/0
psi, v, de = S.T
a = np.column_stack([TS * v * np.cos(psi), TS * np.sin(psi), TS / WHEELBASE * np.tan(de),
                     TS * v / (WHEELBASE * np.cos(de) ** 2)])
iv = ldi.intervals
print("intervals", iv.tolist())
print("a outside interval (max excess)", float(np.max(np.maximum(a - iv[:, 1], iv[:, 0] - a))))
# corners exact
import itertools

cs = np.array(list(itertools.product(*[(l, u) for l, u in zip(lb[1:], ub[1:])])) + [[0, lb[2], 0], [0, ub[2], 0]])
psi, v, de = cs.T
ac = np.column_stack([TS * v * np.cos(psi), TS * np.sin(psi), TS / WHEELBASE * np.tan(de),
                      TS * v / (WHEELBASE * np.cos(de) ** 2)])
print("interval ends attained (max gap lo, hi)", np.max(np.abs(ac.min(0) - iv[:, 0])), np.max(np.abs(ac.max(0) - iv[:, 1])))
# FD Jacobian vs structure at random points
x = np.c_[rng.uniform(-1, 1, 50), S[:50]]; u = np.zeros((50, 2))
h = 1e-6
for k in range(3):
    J = np.zeros((4, 4))
    for j in range(4):
        e = np.zeros(4); e[j] = h
        J[:, j] = (f_np(x[k] + e, u[k], 0) - f_np(x[k] - e, u[k], 0))[0] / (2 * h)
    ak = a[k]
    Jm = np.eye(4); Jm[0, 1] = ak[0]; Jm[0, 2] = ak[1]; Jm[1, 2] = ak[2]; Jm[1, 3] = ak[3]
    print("FD jacobian structure err", np.max(np.abs(J - Jm)))

# 3. LMI feasibility recheck at every vertex with the returned P,K,λ (own eigenvalue test)
lam = d.error.info["lambda"]
G = np.array([0, 1.0, 0, 0])
worst = np.inf
for A in ldi.vertices():
    AK = A + ldi.B @ K
    for wv in (-0.5 * DEG, 0.5 * DEG):
        M = np.block([[lam * P, np.zeros((4, 1))], [np.zeros((1, 4)), np.array([[1 - lam]])]]) - \
            np.c_[AK, G * wv].T @ P @ np.c_[AK, G * wv]
        worst = min(worst, np.linalg.eigvalsh(0.5 * (M + M.T)).min())
print("min eig of the dissipation matrix over vertices (>=0 needed)", worst)

# 4. sampled RPI over z in X, v in U_E (own box), e on ∂E, w in W
L = np.linalg.cholesky(P)
def boundary(m):
    s = rng.normal(size=(m, 4)); s /= np.linalg.norm(s, axis=1)[:, None]
    return np.linalg.solve(L.T, s.T).T
m = 400000
z = rng.uniform(Xlb, Xub, (m, 4))
vlb, vub = Ulb + su, Uub - su
vv = rng.uniform(vlb, vub, (m, 2))
e = boundary(m)
w = rng.choice([-0.5 * DEG, 0.5 * DEG], m) * (rng.random(m) < 0.7) + rng.uniform(-0.5, 0.5, m) * DEG * (rng.random(m) < 0.3)
w = np.clip(w, -0.5 * DEG, 0.5 * DEG)
en = f_np(z + e, vv + e @ K.T, w) - f_np(z, vv, np.zeros(m))
Vn = np.einsum("ij,jk,ik->i", en, P, en)
k = int(np.argmax(Vn))
print(f"sampled RPI: max V(e+) - 1 = {Vn[k]-1:.4e} at z={z[k]}, w={w[k]}")
# also: z anywhere in the LDI domain (z + segment in D) - the claim's full coverage
zD = rng.uniform(np.r_[-1, lb[1:]], np.r_[1, ub[1:]], (m, 4))
eD = boundary(m)
inD = np.all((zD + eD)[:, 1:] >= lb[1:]) & np.all((zD + eD)[:, 1:] <= ub[1:])
en = f_np(zD + eD, vv + eD @ K.T, w) - f_np(zD, vv, np.zeros(m))
okD = np.all(((zD + eD)[:, 1:] >= lb[1:]) & ((zD + eD)[:, 1:] <= ub[1:]), axis=1)
VnD = np.einsum("ij,jk,ik->i", en, P, en)[okD]
print(f"sampled RPI, z and z+e anywhere in D ({okD.sum()} samples): max V(e+) - 1 = {VnD.max()-1:.4e}")

# 5. multi-start NLP: max V(e+) over z in X, v in U_E, e'Pe<=1, w in W
opti = ca.Opti()
zs, vs, ss, ws = opti.variable(4), opti.variable(2), opti.variable(4), opti.variable(1)
Linv_T = np.linalg.inv(L).T
es = ca.mtimes(ca.DM(Linv_T), ss)
def f_ca(x, u, w):
    return ca.vertcat(x[0] + TS * x[2] * ca.sin(x[1]), x[1] + TS * x[2] / WHEELBASE * ca.tan(x[3]) + w,
                      x[2] + TS * u[1], x[3] + u[0])
enc = f_ca(zs + es, vs + ca.mtimes(ca.DM(K), es), ws) - f_ca(zs, vs, 0)
opti.minimize(-ca.mtimes([enc.T, ca.DM(P), enc]))
opti.subject_to(opti.bounded(Xlb, zs, Xub)); opti.subject_to(opti.bounded(vlb, vs, vub))
opti.subject_to(ca.sumsqr(ss) <= 1); opti.subject_to(opti.bounded(-0.5 * DEG, ws, 0.5 * DEG))
opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "tol": 1e-10})
best, nconv = -np.inf, 0
for i in range(40):
    opti.set_initial(zs, rng.uniform(Xlb, Xub)); opti.set_initial(vs, rng.uniform(vlb, vub))
    s0 = rng.normal(size=4); opti.set_initial(ss, s0 / np.linalg.norm(s0))
    opti.set_initial(ws, rng.choice([-1, 1]) * 0.5 * DEG)
    try:
        sol = opti.solve(); nconv += 1
        val = -sol.value(opti.f) - 1
        if val > best:
            best, arg = val, (sol.value(zs), sol.value(ws))
    except RuntimeError:
        pass
print(f"NLP RPI worst-case ({nconv}/40 converged): max V(e+) - 1 = {best:.4e} at z={arg[0]}, w={arg[1]}")

# 6. terminal set: h_f invariance and decrease, own
cbf = d.cbf
Pf, Kf, xs = cbf.P, cbf.K, cbf.x_s
Lf = np.linalg.cholesky(Pf)
s = rng.normal(size=(m, 4)); s /= np.linalg.norm(s, axis=1)[:, None]
s[m // 2:] *= rng.random((m - m // 2, 1)) ** 0.25
dz = np.linalg.solve(Lf.T, s.T).T
zn = f_np(xs + dz, dz @ Kf.T, np.zeros(m)) - xs
hn = np.einsum("ij,jk,ik->i", zn, Pf, zn) - 1
h0 = np.einsum("ij,jk,ik->i", dz, Pf, dz) - 1
print(f"terminal: max h_f(z+) = {hn.max():.4e}, max (h_f(z+)+1) - 0.99(h_f(z)+1) = {np.max(hn + 1 - 0.99 * (h0 + 1)):.4e}")
# S_f inside X_E tightened by Δ_{N-1}, π_f(S_f) in U_E (support functions)
Efi = np.linalg.inv(Pf)
dN = d.deltas[-1]
rows_x = max(float(a @ xs + np.sqrt(a @ Efi @ a) - (b - dN)) for a, b in zip(XE.H, XE.h))
rows_u = max(float(np.sqrt(a @ Kf @ Efi @ Kf.T @ a) - b) for a, b in zip(UE.H, UE.h))
print(f"S_f rows: state {rows_x:.4e} input {rows_u:.4e} (<= 0 needed)")
# S_f within the LDI domain
sfa = np.sqrt(np.diag(Efi))
print("S_f box", (xs - sfa).tolist(), (xs + sfa).tolist(), "domain", lb.tolist(), ub.tolist())
print("gamma_f", cbf.gamma_f, "time", time.time() - t0)
