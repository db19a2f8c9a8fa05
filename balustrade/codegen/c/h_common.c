/* bal/h_common.c: the two emitted CasADi functions of the steps built on the learned
 * h^ (bal/approx.c, Algorithm 7.5; bal/grid.c, Algorithm 8.7): A_h(x) = h^(x) and
 * A_h_next(x, u) = h^(f(x, u)), with their memories wk->hmem, wk->nmem and the shared
 * work vectors harg, hres, hiw, hw of the work struct. Included by both after
 * bal/step_common.c.
 */
#include <math.h>

/* check out the memories of A_h and A_h_next; -1 (nothing kept) if one fails */
static int BAL_QX(h_acquire)(BAL_QX(work)* wk) {
  BAL_QX(h_incref)();
  wk->hmem = BAL_QX(h_checkout)();
  BAL_QX(h_next_incref)();
  wk->nmem = BAL_QX(h_next_checkout)();
  if (wk->hmem < 0 || wk->nmem < 0) {
    if (wk->hmem >= 0) BAL_QX(h_release)(wk->hmem);
    if (wk->nmem >= 0) BAL_QX(h_next_release)(wk->nmem);
    BAL_QX(h_decref)();
    BAL_QX(h_next_decref)();
    return -1;
  }
  return 0;
}

/* release what BAL_QX(h_acquire) checked out */
static void BAL_QX(h_release_all)(BAL_QX(work)* wk) {
  BAL_QX(h_next_release)(wk->nmem);
  BAL_QX(h_next_decref)();
  BAL_QX(h_release)(wk->hmem);
  BAL_QX(h_decref)();
}

/* h^(x); NAN if the evaluation fails */
static casadi_real BAL_QX(eval_h)(BAL_QX(work)* wk, const casadi_real* x) {
  casadi_real v = NAN;
  wk->harg[0] = x;
  wk->hres[0] = &v;
  if (BAL_QX(h)(wk->harg, wk->hres, wk->hiw, wk->hw, wk->hmem)) return NAN;
  return v;
}

/* h^(f(x, u)); NAN if the evaluation fails */
static casadi_real BAL_QX(eval_h_next)(BAL_QX(work)* wk, const casadi_real* x,
                                       const casadi_real* u) {
  casadi_real v = NAN;
  wk->harg[0] = x;
  wk->harg[1] = u;
  wk->hres[0] = &v;
  if (BAL_QX(h_next)(wk->harg, wk->hres, wk->hiw, wk->hw, wk->nmem)) return NAN;
  return v;
}
