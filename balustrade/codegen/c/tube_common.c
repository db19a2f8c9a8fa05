/* bal/tube_common.c: the pieces of the tube-based control steps Q = BAL_STEP shared by
 * bal/robust.c (Algorithm 5.2) and bal/multiobj.c (Algorithm 6.4): the applied input
 * (5.16) u = v_0 + K(x - z_0) and the next candidate (5.17)/(6.14) from Q_cand. Included
 * by both after their constants Q_kappa (K, NU x NX, column-major); the work struct has
 * the candidate members cz, cv, cxi, cxi_N, ch, the scratch nz, nv, nxi, nxi_N, nh, nok
 * (bal/common.h BAL_TUBE_CANDIDATE_MEMBERS) and the CasADi work vectors arg, res, iw, w.
 */
#include <string.h>

/* u := v0 + K (x - z0), in the order of balustrade.dsl.error_sets.ErrorSet.kappa (the
   Python controllers' u = v0 + kappa(x - z0)): (K e)_i summed left to right from its first
   term, then added to v0, so that C and Python round alike (bitwise equal inputs) */
static void BAL_QX(applied)(const casadi_real* x, const casadi_real* z0,
                            const casadi_real* v0, casadi_real* u) {
  casadi_int i, j;
  casadi_real acc;
  for (i = 0; i < BAL_QX(NU); ++i) {
    acc = BAL_QX(kappa)[i] * (x[0] - z0[0]);
    for (j = 1; j < BAL_QX(NX); ++j) acc += BAL_QX(kappa)[i + j * BAL_QX(NU)] * (x[j] - z0[j]);
    u[i] = v0[i] + acc;
  }
}

/* The next candidate (5.17)/(6.14) from (z, v, xi) (Q_cand); kept only if its terminal
   input was computed exactly, else dropped (have_cand = cand_exact = 0). z, v, xi may
   point into the current candidate: Q_cand writes the scratch members first. */
static void BAL_QX(make_candidate)(BAL_QX(work)* wk, const casadi_real* z,
                                   const casadi_real* v, const casadi_real* xi) {
  wk->arg[0] = z;
  wk->arg[1] = v;
  wk->arg[2] = xi;
  wk->res[0] = wk->nz;
  wk->res[1] = wk->nv;
  wk->res[2] = wk->nxi;
  wk->res[3] = &wk->nxi_N;
  wk->res[4] = &wk->nh;
  wk->res[5] = &wk->nok;
  if (BAL_QX(cand)(wk->arg, wk->res, wk->iw, wk->w, 0) || !(wk->nok > 0.5)) {
    wk->have_cand = 0;
    wk->cand_exact = 0;
    return;
  }
  memcpy(wk->cz, wk->nz, sizeof(wk->cz));
  memcpy(wk->cv, wk->nv, sizeof(wk->cv));
  memcpy(wk->cxi, wk->nxi, sizeof(wk->cxi));
  wk->cxi_N = wk->nxi_N;
  wk->ch = wk->nh;
  wk->have_cand = 1;
  wk->cand_exact = 1;
}
