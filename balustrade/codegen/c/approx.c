/* bal/approx.c: Algorithm 7.5 A = BAL_STEP (bal/approx.h) with the fallbacks of
 * balustrade.control.approximate. Included by the generated <name>.c after the problems
 * A_dec (7.6) and A_filter (7.5). From <name>_config.h: A_NX, A_NU, A_NC (candidates: 2 +
 * grid points), A_N_LOCAL, A_RHO, A_CERTIFY, A_EXACT_SHORTCUT, the box U (A_U_LB, A_U_UB),
 * the grid A_GRID and the offsets of the problems (A_dec_W_u, A_filter_P_x0, ...).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "step_common.c"
#include "h_common.c"
#if BAL_QX(NET)
#include "approx_net.c"
#endif

/* h^(x) and h^(f(x, u)): from the network's weights when A_NET (bal/approx_net.c, the same
   values), else the CasADi functions A_h, A_h_next */
static casadi_real BAL_QX(value_h)(BAL_QX(work)* wk, const casadi_real* x) {
#if BAL_QX(NET)
  (void) wk;
  (void) &BAL_QX(eval_h); /* the CasADi functions stay in the library, unused here */
  (void) &BAL_QX(eval_h_next);
  return BAL_QX(net_eval)(x);
#else
  return BAL_QX(eval_h)(wk, x);
#endif
}

static casadi_real BAL_QX(value_h_next)(BAL_QX(work)* wk, const casadi_real* x,
                                        const casadi_real* u) {
#if BAL_QX(NET)
  return BAL_QX(net_eval_next)(wk, x, u);
#else
  return BAL_QX(eval_h_next)(wk, x, u);
#endif
}

static const casadi_real BAL_QX(u_lb)[BAL_QX(NU)] = BAL_QX(U_LB);
static const casadi_real BAL_QX(u_ub)[BAL_QX(NU)] = BAL_QX(U_UB);
static const casadi_real BAL_QX(grid)[BAL_QX(NC) - 2][BAL_QX(NU)] = BAL_QX(GRID);

static int BAL_QX(in_box)(const casadi_real* u, casadi_real tol) {
  casadi_int i;
  for (i = 0; i < BAL_QX(NU); ++i) {
    if (!(u[i] >= BAL_QX(u_lb)[i] - tol && u[i] <= BAL_QX(u_ub)[i] + tol)) return 0;
  }
  return 1;
}

/* h^(f(x, u_p)) for this step's proposal u_p = wk->u_p, evaluated once per step: the same
   function at the same arguments, so reusing it changes no value (only the time) */
static casadi_real BAL_QX(h_up)(BAL_QX(work)* wk, const casadi_real* x) {
  if (!wk->h_up_ready) {
    wk->h_up = BAL_QX(value_h_next)(wk, x, wk->u_p);
    wk->h_up_ready = 1;
  }
  return wk->h_up;
}

/* 1 if a equals b entry by entry (==, as numpy's (a == b).all()) */
static int BAL_QX(same_input)(const casadi_real* a, const casadi_real* b) {
  casadi_int i;
  for (i = 0; i < BAL_QX(NU); ++i) {
    if (!(a[i] == b[i])) return 0;
  }
  return 1;
}

int BAL_QX(init)(BAL_QX(work)* wk) {
  wk->ready = 0;
  if (BAL_QX(dec_init)(&wk->dec)) return -1;
  if (BAL_QX(filter_init)(&wk->filter)) {
    BAL_QX(dec_finalize)(&wk->dec);
    return -1;
  }
  if (BAL_QX(h_acquire)(wk)) {
    BAL_QX(filter_finalize)(&wk->filter);
    BAL_QX(dec_finalize)(&wk->dec);
    return -1;
  }
#if BAL_QX(NET)
  BAL_QX(f_incref)();
  wk->fmem = BAL_QX(f_checkout)();
  if (wk->fmem < 0) {
    BAL_QX(f_decref)();
    BAL_QX(h_release_all)(wk);
    BAL_QX(filter_finalize)(&wk->filter);
    BAL_QX(dec_finalize)(&wk->dec);
    return -1;
  }
#endif
  wk->certify = BAL_QX(CERTIFY);
  BAL_QX(reset)(wk);
  wk->ready = 1;
  return 0;
}

void BAL_QX(finalize)(BAL_QX(work)* wk) {
  if (!wk->ready) return;
#if BAL_QX(NET)
  BAL_QX(f_release)(wk->fmem);
  BAL_QX(f_decref)();
#endif
  BAL_QX(h_release_all)(wk);
  BAL_QX(filter_finalize)(&wk->filter);
  BAL_QX(dec_finalize)(&wk->dec);
  wk->ready = 0;
}

BAL_DEFINE_ALLOC_FREE(BAL_QX)

void BAL_QX(reset)(BAL_QX(work)* wk) {
  wk->n_steps = wk->n_certified = wk->n_solved = wk->n_fallbacks = 0;
  wk->n_proposal_feasible = 0;
  wk->dec_status = wk->filter_status = BAL_NOT_RUN;
  wk->h_x = wk->dh = wk->best_v = NAN;
  wk->n_replaced = 0;
}

void BAL_QX(set_certify)(BAL_QX(work)* wk, int certify) { wk->certify = certify; }
casadi_real BAL_QX(dh)(const BAL_QX(work)* wk) { return wk->dh; }
int BAL_QX(proposal_replaced)(const BAL_QX(work)* wk) { return wk->n_replaced; }
int BAL_QX(inaccurate)(const BAL_QX(work)* wk) {
  return wk->filter_status == BAL_OK && BAL_QX(filter_inaccurate)(&wk->filter);
}
long BAL_QX(counter)(const BAL_QX(work)* wk, int which) {
  return which == 0   ? wk->n_steps
         : which == 1 ? wk->n_certified
         : which == 2 ? wk->n_solved
         : which == 3 ? wk->n_fallbacks
                      : wk->n_proposal_feasible;
}

/* (7.6) by screened multi-start; returns 1 if a finite minimizer was found. */
static int BAL_QX(max_decrease)(BAL_QX(work)* wk, const casadi_real* x,
                                const casadi_real* u_p) {
  casadi_int i, j, k, n_tried = 0;
  int found = 0, same, key;
  casadi_real zero[BAL_QX(NU)], v;
  const casadi_real *c, *t, *u_loc;
  for (i = 0; i < BAL_QX(NU); ++i) zero[i] = 0.0;
  bal_clip(zero, BAL_QX(u_lb), BAL_QX(u_ub), wk->cand, BAL_QX(NU));
  bal_clip(u_p, BAL_QX(u_lb), BAL_QX(u_ub), wk->cand + BAL_QX(NU), BAL_QX(NU));
  for (k = 2; k < BAL_QX(NC); ++k) {
    for (i = 0; i < BAL_QX(NU); ++i) wk->cand[k * BAL_QX(NU) + i] = BAL_QX(grid)[k - 2][i];
  }
  for (k = 0; k < BAL_QX(NC); ++k) {
    c = wk->cand + k * BAL_QX(NU);
    /* candidate 1 is clip(u_p): when it is u_p itself, h^(f(x, u_p)) of this step */
    v = k == 1 && BAL_QX(same_input)(c, u_p) ? BAL_QX(h_up)(wk, x)
                                             : BAL_QX(value_h_next)(wk, x, c);
    wk->values[k] = isfinite(v) ? v : INFINITY;
  }
  /* stable insertion sort of the candidate indices by value */
  for (k = 0; k < BAL_QX(NC); ++k) {
    key = (int) k;
    for (j = k - 1; j >= 0 && wk->values[wk->order[j]] > wk->values[key]; --j) {
      wk->order[j + 1] = wk->order[j];
    }
    wk->order[j + 1] = key;
  }
  for (i = 0; i < BAL_QX(NU); ++i) wk->best_u[i] = wk->cand[wk->order[0] * BAL_QX(NU) + i];
  wk->best_v = wk->values[wk->order[0]];
  wk->dec_status = BAL_NOT_RUN;
  for (k = 0; k < BAL_QX(NC) && n_tried < BAL_QX(N_LOCAL); ++k) {
    c = wk->cand + wk->order[k] * BAL_QX(NU);
    same = 0;
    for (j = 0; j < n_tried && !same; ++j) { /* numpy.allclose(c, t) */
      t = wk->cand + wk->tried[j] * BAL_QX(NU);
      same = 1;
      for (i = 0; i < BAL_QX(NU); ++i) {
        if (!(fabs(c[i] - t[i]) <= 1e-8 + 1e-5 * fabs(t[i]))) same = 0;
      }
    }
    if (same) continue;
    wk->tried[n_tried++] = wk->order[k];
    BAL_QX(dec_cold_start)(&wk->dec);
    for (i = 0; i < BAL_QX(NU); ++i) wk->dec.x0[BAL_QX(dec_W_u) + i] = c[i];
    for (i = 0; i < BAL_QX(NX); ++i) wk->p_dec[BAL_QX(dec_P_x0) + i] = x[i];
    wk->dec_status = BAL_QX(dec_solve)(&wk->dec, wk->p_dec);
    if (!BAL_SOLVED(wk->dec_status)) continue;
    u_loc = wk->dec.x + BAL_QX(dec_W_u);
    if (!BAL_QX(in_box)(u_loc, 1e-7)) continue;
    found = 1;
    v = BAL_QX(value_h_next)(wk, x, u_loc);
    if (v < wk->best_v) {
      wk->best_v = v;
      for (i = 0; i < BAL_QX(NU); ++i) wk->best_u[i] = u_loc[i];
    }
  }
  return found || isfinite(wk->best_v);
}

int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p_in, casadi_real* u_out,
                 casadi_real* h_out, int* status, BAL_QX(work)* wk) {
  casadi_int i;
  const casadi_real* u_p;
  if (!x || !u_p_in || !u_out || !h_out || !status || !wk) {
    if (status) *status = BAL_APPROX_BAD_INPUT;
    return BAL_APPROX_BAD_INPUT;
  }
  wk->n_steps++;
  wk->dec_status = wk->filter_status = BAL_NOT_RUN;
  wk->dh = NAN;
  wk->h_up_ready = 0;
  *h_out = NAN;
  wk->n_replaced = bal_read_proposal(u_p_in, wk->u_p, BAL_QX(NU));
  u_p = wk->u_p;
  if (!bal_finite(x, BAL_QX(NX))) {
    /* nothing is evaluated with a NaN or inf state (as balustrade.control.approximate:
       "non_finite_state", projected proposal) */
    wk->n_fallbacks++;
    wk->dec_status = wk->filter_status = BAL_BAD_INPUT;
    bal_clip(u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
    *status = BAL_APPROX_BAD_INPUT;
    return *status;
  }
  /* line 4: certification by one evaluation */
  if (wk->certify && BAL_QX(in_box)(u_p, 1e-9) && BAL_QX(h_up)(wk, x) <= 0.0) {
    wk->n_certified++;
    for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = u_p[i];
    *status = BAL_APPROX_CERTIFIED;
    return *status;
  }
  wk->n_solved++;
  wk->h_x = BAL_QX(value_h)(wk, x);
  *h_out = wk->h_x;
  if (!BAL_QX(max_decrease)(wk, x, u_p)) {
    wk->n_fallbacks++;
    for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = wk->best_u[i];
    *status = BAL_APPROX_GRID_MINIMIZER;
    return *status;
  }
  wk->dh = wk->h_x - wk->best_v;
  /* exact shortcut: u_p feasible in (7.5), bound max(-rho dh, -dh), is its minimizer */
  if (BAL_QX(EXACT_SHORTCUT) && BAL_QX(in_box)(u_p, 1e-9)
      && BAL_QX(h_up)(wk, x) - wk->h_x
             <= fmax(-BAL_QX(RHO) * wk->dh, -wk->dh)) {
    wk->n_proposal_feasible++;
    for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = u_p[i];
    *status = BAL_APPROX_PROPOSAL_FEASIBLE;
    return *status;
  }
  /* (7.5) warm-started at the (7.6) minimizer */
  for (i = 0; i < BAL_QX(NX); ++i) wk->p_filter[BAL_QX(filter_P_x0) + i] = x[i];
  for (i = 0; i < BAL_QX(NU); ++i) wk->p_filter[BAL_QX(filter_P_u_p) + i] = u_p[i];
  wk->p_filter[BAL_QX(filter_P_dh)] = wk->dh;
  wk->p_filter[BAL_QX(filter_P_rho)] = BAL_QX(RHO);
  BAL_QX(filter_cold_start)(&wk->filter);
  for (i = 0; i < BAL_QX(NU); ++i) wk->filter.x0[BAL_QX(filter_W_u) + i] = wk->best_u[i];
  wk->filter_status = BAL_QX(filter_solve)(&wk->filter, wk->p_filter);
  if (BAL_SOLVED(wk->filter_status) && BAL_QX(in_box)(wk->filter.x + BAL_QX(filter_W_u), 1e-7)) {
    for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = wk->filter.x[BAL_QX(filter_W_u) + i];
    *status = wk->filter_status == BAL_OK ? BAL_APPROX_OK : BAL_APPROX_FILTER_FEASIBLE;
  } else {
    wk->n_fallbacks++;
    for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = wk->best_u[i];
    *status = BAL_APPROX_MAX_DECREASE;
  }
  return *status;
}
