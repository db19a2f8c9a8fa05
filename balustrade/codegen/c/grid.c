/* bal/grid.c: Algorithm 8.7 A = BAL_STEP (bal/grid.h) with the fallbacks of
 * balustrade.control.approximate.GridPCBFFilter. From <name>_config.h: A_NX, A_NU, A_M
 * (offsets), A_RHO, the box U (A_U_LB, A_U_UB), A_OFFSETS, A_SCALE, A_U_INIT.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "step_common.c"
#include "h_common.c"

static const casadi_real BAL_QX(u_lb)[BAL_QX(NU)] = BAL_QX(U_LB);
static const casadi_real BAL_QX(u_ub)[BAL_QX(NU)] = BAL_QX(U_UB);
static const casadi_real BAL_QX(offsets)[BAL_QX(M)][BAL_QX(NU)] = BAL_QX(OFFSETS);
static const casadi_real BAL_QX(scale)[BAL_QX(NU)] = BAL_QX(SCALE);
static const casadi_real BAL_QX(u_init)[BAL_QX(NU)] = BAL_QX(U_INIT);

int BAL_QX(init)(BAL_QX(work)* wk) {
  wk->ready = 0;
  if (BAL_QX(h_acquire)(wk)) return -1;
  BAL_QX(reset)(wk);
  wk->ready = 1;
  return 0;
}

void BAL_QX(finalize)(BAL_QX(work)* wk) {
  if (!wk->ready) return;
  BAL_QX(h_release_all)(wk);
  wk->ready = 0;
}

BAL_DEFINE_ALLOC_FREE(BAL_QX)

void BAL_QX(reset)(BAL_QX(work)* wk) {
  casadi_real u[BAL_QX(NU)];
  bal_read_proposal(BAL_QX(u_init), u, BAL_QX(NU));
  bal_clip(u, BAL_QX(u_lb), BAL_QX(u_ub), wk->u_prev, BAL_QX(NU));
  wk->n_steps = wk->n_decrease_infeasible = 0;
  wk->n_cand = wk->n_replaced = 0;
}

int BAL_QX(n_candidates)(const BAL_QX(work)* wk) { return wk->n_cand; }
int BAL_QX(proposal_replaced)(const BAL_QX(work)* wk) { return wk->n_replaced; }
long BAL_QX(counter)(const BAL_QX(work)* wk, int which) {
  return which == 0 ? wk->n_steps : wk->n_decrease_infeasible;
}
const casadi_real* BAL_QX(u_prev)(const BAL_QX(work)* wk) { return wk->u_prev; }

/* -1, 0, 1 as row a is lexicographically before, equal to, after row b */
static int BAL_QX(lex)(const casadi_real* a, const casadi_real* b) {
  casadi_int i;
  for (i = 0; i < BAL_QX(NU); ++i) {
    if (a[i] < b[i]) return -1;
    if (a[i] > b[i]) return 1;
  }
  return 0;
}

/* Step 1: the rows of wk->cand (unsorted, u_prev + offsets, clipped, rounded), their
   sorted order without duplicates in wk->order[0 .. n_cand) */
static void BAL_QX(candidates)(BAL_QX(work)* wk) {
  casadi_int i, k;
  int j, key, n = 0;
  casadi_real v, *c;
  for (k = 0; k < BAL_QX(M); ++k) {
    c = wk->cand + k * BAL_QX(NU);
    for (i = 0; i < BAL_QX(NU); ++i) {
      v = wk->u_prev[i] + BAL_QX(offsets)[k][i];
      v = fmin(fmax(v, BAL_QX(u_lb)[i]), BAL_QX(u_ub)[i]);
      c[i] = rint(v * 1e12) / 1e12; /* numpy.round(v, 12) */
    }
  }
  /* insertion sort (the offsets come nearly sorted); equal rows are dropped */
  for (k = 0; k < BAL_QX(M); ++k) {
    key = (int) k;
    c = wk->cand + k * BAL_QX(NU);
    for (j = n - 1; j >= 0 && BAL_QX(lex)(wk->cand + wk->order[j] * BAL_QX(NU), c) > 0; --j) {
    }
    if (j >= 0 && BAL_QX(lex)(wk->cand + wk->order[j] * BAL_QX(NU), c) == 0) continue;
    memmove(wk->order + j + 2, wk->order + j + 1, (size_t) (n - j - 1) * sizeof(int));
    wk->order[j + 1] = key;
    ++n;
  }
  wk->n_cand = n;
}

int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p_in, casadi_real* u_out,
                 casadi_real* h_out, int* status, BAL_QX(work)* wk) {
  casadi_int i;
  int k, best = -1, any_ok = 0;
  casadi_real h_x = NAN, thr, d, e, best_d = INFINITY, *c;
  if (!x || !u_p_in || !u_out || !h_out || !status || !wk) {
    if (status) *status = BAL_GRID_BAD_INPUT;
    return BAL_GRID_BAD_INPUT;
  }
  wk->n_steps++;
  *h_out = NAN;
  wk->n_replaced = bal_read_proposal(u_p_in, wk->u_p, BAL_QX(NU));
  if (!bal_finite(x, BAL_QX(NX))) {
    /* keep the last input (Algorithm 8.7 is rate-limited around it) */
    wk->n_cand = 0;
    for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = wk->u_prev[i];
    *status = BAL_GRID_BAD_INPUT;
    return *status;
  }
  BAL_QX(candidates)(wk);
  /* step 2: every candidate, one loop */
  for (k = 0; k < wk->n_cand; ++k) {
    casadi_real v = BAL_QX(eval_h_next)(wk, x, wk->cand + wk->order[k] * BAL_QX(NU));
    wk->values[k] = isfinite(v) ? v : INFINITY;
  }
  h_x = BAL_QX(eval_h)(wk, x);
  *h_out = h_x;
  /* step 3: the first closest admissible candidate, else the first grid minimizer */
  thr = BAL_QX(RHO) * h_x;
  for (k = 0; k < wk->n_cand; ++k) {
    if (!(wk->values[k] <= thr)) continue;
    c = wk->cand + wk->order[k] * BAL_QX(NU);
    d = 0.0;
    for (i = 0; i < BAL_QX(NU); ++i) {
      e = (c[i] - wk->u_p[i]) / BAL_QX(scale)[i];
      d += e * e;
    }
    if (!any_ok || d < best_d) {
      best_d = d;
      best = k;
    }
    any_ok = 1;
  }
  if (any_ok) {
    *status = BAL_GRID_OK;
  } else {
    best = 0;
    for (k = 1; k < wk->n_cand; ++k) {
      if (wk->values[k] < wk->values[best]) best = k;
    }
    wk->n_decrease_infeasible++;
    *status = BAL_GRID_NO_DECREASE;
  }
  c = wk->cand + wk->order[best] * BAL_QX(NU);
  for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = wk->u_prev[i] = c[i];
  return *status;
}
