/* bal/pcbf.c: the PCBF control step Q = BAL_STEP ((2.24) then (2.23), bal/pcbf.h) with the
 * fallbacks of balustrade.control.pcbf. Included by the generated <name>.c after the
 * problems Q_slack and Q_filter. From <name>_config.h: Q_NX, Q_NU, Q_N, Q_N_XI (slacks xi),
 * Q_ZERO_TOL, the box U (Q_U_LB, Q_U_UB), the offsets of the problems (Q_slack_P_x0, ...)
 * and Q_SHARED(X): the variables (2.23) shares with (2.24) (offset in (2.24), offset in
 * (2.23), size), its warm start before its first success.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "step_common.c"

static const casadi_real BAL_QX(u_lb)[BAL_QX(NU)] = BAL_QX(U_LB);
static const casadi_real BAL_QX(u_ub)[BAL_QX(NU)] = BAL_QX(U_UB);

/* Layout element i of a problem's x (stage order: x[take[i]], projected onto the layout's
   bounds unless `raw`, as the backend reports the point) */
static casadi_real BAL_QX(layout_at)(const casadi_real* x, const casadi_int* take,
                                     const casadi_real* lb, const casadi_real* ub,
                                     casadi_int i, int raw) {
  casadi_real v;
  if (!take) return x[i];
  v = x[take[i]];
  return raw ? v : fmin(fmax(v, lb[i]), ub[i]);
}
#if BAL_QX(slack_STAGED)
static const casadi_int BAL_QX(s_take)[BAL_QX(slack_NW)] = BAL_QX(slack_TAKE);
static const casadi_real BAL_QX(s_lbl)[BAL_QX(slack_NW)] = BAL_QX(slack_LBX_L);
static const casadi_real BAL_QX(s_ubl)[BAL_QX(slack_NW)] = BAL_QX(slack_UBX_L);
#define BAL_PCBF_S_MAP BAL_QX(s_take), BAL_QX(s_lbl), BAL_QX(s_ubl)
#else
#define BAL_PCBF_S_MAP 0, 0, 0
#endif
#if BAL_QX(filter_STAGED)
static const casadi_int BAL_QX(f_take)[BAL_QX(filter_NW)] = BAL_QX(filter_TAKE);
static const casadi_real BAL_QX(f_lbl)[BAL_QX(filter_NW)] = BAL_QX(filter_LBX_L);
static const casadi_real BAL_QX(f_ubl)[BAL_QX(filter_NW)] = BAL_QX(filter_UBX_L);
#define BAL_PCBF_F_MAP BAL_QX(f_take), BAL_QX(f_lbl), BAL_QX(f_ubl)
#else
#define BAL_PCBF_F_MAP 0, 0, 0
#endif
/* layout element i of (2.24)'s point (a certified shifted plan is used as it is, as the
   Python filter uses the candidate) and of (2.23)'s */
#define BAL_PCBF_SLACK(i) \
  BAL_QX(layout_at)(wk->slack.x, BAL_PCBF_S_MAP, (i), wk->shift_certified || wk->cert_first)
#define BAL_PCBF_FILTER(i) BAL_QX(layout_at)(wk->filter.x, BAL_PCBF_F_MAP, (i), 0)

/* (2.24)'s warm start := the primal of its point, zero multipliers (the backend's warm
   start from a Solution that did not converge, or from the certificate's candidate) */
static void BAL_QX(pcbf_slack_keep)(BAL_QX(work)* wk) {
#if BAL_QX(slack_STAGED)
  casadi_int i;
  BAL_QX(slack_cold_start)(&wk->slack);
  for (i = 0; i < BAL_QX(slack_N_USER); ++i) {
    wk->slack.x0[BAL_QX(s_take)[i]] = BAL_PCBF_SLACK(i);
  }
#else
  BAL_QX(slack_warm_start_primal)(&wk->slack);
#endif
}

/* (2.24) in stage order: h_PB is its declared cost at the projected layout point, as the
   backend reports Solution.objective (not the solver's value at its relaxed point) */
static void BAL_QX(pcbf_slack_cost)(BAL_QX(work)* wk) {
#if BAL_QX(slack_STAGED)
  casadi_int i;
  casadi_real f = NAN;
  if (!bal_finite(wk->slack.x, BAL_QX(slack_NW))) return;
  for (i = 0; i < BAL_QX(slack_NW); ++i) wk->s_lay[i] = BAL_QX(layout_at)(
      wk->slack.x, BAL_PCBF_S_MAP, i, 0);
  wk->oarg[0] = wk->s_lay;
  wk->oarg[1] = wk->p_slack;
  wk->ores[0] = &f;
  if (BAL_QX(slack_obj)(wk->oarg, wk->ores, wk->oiw, wk->ow, 0)) f = NAN;
  wk->slack.f = f;
#else
  (void)wk;
#endif
}

#if BAL_QX(SHIFT_CERT)
/* init/finalize: the two problems and the memory of Q_shift_cert */
int BAL_QX(init)(BAL_QX(work)* wk) {
  wk->ready = 0;
  if (BAL_QX(slack_init)(&wk->slack)) return -1;
  if (BAL_QX(filter_init)(&wk->filter)) {
    BAL_QX(slack_finalize)(&wk->slack);
    return -1;
  }
  BAL_QX(shift_cert_incref)();
  wk->cmem = BAL_QX(shift_cert_checkout)();
  if (wk->cmem < 0) {
    BAL_QX(shift_cert_decref)();
    BAL_QX(filter_finalize)(&wk->filter);
    BAL_QX(slack_finalize)(&wk->slack);
    return -1;
  }
  BAL_QX(reset)(wk);
  wk->ready = 1;
  return 0;
}

void BAL_QX(finalize)(BAL_QX(work)* wk) {
  if (!wk->ready) return;
  BAL_QX(shift_cert_release)(wk->cmem);
  BAL_QX(shift_cert_decref)();
  BAL_QX(filter_finalize)(&wk->filter);
  BAL_QX(slack_finalize)(&wk->slack);
  wk->ready = 0;
}

/* The shifted plan (ShiftedCertificate.check): the remaining inputs of the plan, then 0,
   rolled out from x; 1 if it meets every row and bound of (2.24) within CERT_TOL with cost
   <= ZERO_TOL, and then the candidate is in wk->slack.x (declared variables) and
   wk->slack.f; 0 (wk->slack untouched) otherwise. Needs a plan. */
static int BAL_QX(shift_eval)(BAL_QX(work)* wk, const casadi_real* x) {
  casadi_int m;
  memset(wk->cert_U, 0, sizeof(wk->cert_U));
  m = BAL_QX(N) - wk->plan_age - 1; /* inputs u_{age+1} ... u_{N-1} of the plan, then 0 */
  if (m > 0) {
    memcpy(wk->cert_U, wk->plan + (wk->plan_age + 1) * BAL_QX(NU),
           (size_t)(m * BAL_QX(NU)) * sizeof(casadi_real));
  }
  wk->cert_v = wk->cert_f = NAN;
  wk->carg[0] = x;
  wk->carg[1] = wk->cert_U;
  wk->cres[0] = wk->cert_w;
  wk->cres[1] = &wk->cert_v;
  wk->cres[2] = &wk->cert_f;
  if (BAL_QX(shift_cert)(wk->carg, wk->cres, wk->ciw, wk->cw, wk->cmem)) return 0;
  /* a non-finite roll-out certifies nothing (fmax would skip a NaN row) */
  if (!bal_finite(wk->cert_w, BAL_QX(slack_N_USER)) || !isfinite(wk->cert_v) ||
      !isfinite(wk->cert_f)) {
    return 0;
  }
  if (!(wk->cert_v <= BAL_QX(CERT_TOL) && fabs(wk->cert_f) <= BAL_QX(ZERO_TOL))) return 0;
#if BAL_QX(slack_STAGED)
  for (m = 0; m < BAL_QX(slack_N_USER); ++m) wk->slack.x[BAL_QX(s_take)[m]] = wk->cert_w[m];
#else
  memcpy(wk->slack.x, wk->cert_w, BAL_QX(slack_N_USER) * sizeof(casadi_real));
#endif
  wk->slack.f = wk->cert_f;
  return 1;
}

/* The shifted plan as the (2.24) point (PCBFSafetyFilter._shifted): only when a plan exists
   and (2.24) did not give h_PB within max(ZERO_TOL, EPS) itself (`usable`: converged,
   feasible or a feasible truncated iterate). */
static int BAL_QX(shift_check)(BAL_QX(work)* wk, const casadi_real* x, int usable) {
  casadi_real h = wk->slack.f;
  if (!wk->have_plan) return 0;
  if (usable && h <= fmax(BAL_QX(ZERO_TOL), BAL_QX(EPS))) return 0;
  if (!BAL_QX(shift_eval)(wk, x)) return 0;
  wk->h_solver = usable ? h : NAN;
  return 1;
}
#else
BAL_DEFINE_PAIR_INIT_FINALIZE(BAL_QX, slack, filter)
#endif

BAL_DEFINE_ALLOC_FREE(BAL_QX)

void BAL_QX(reset)(BAL_QX(work)* wk) {
  BAL_QX(slack_cold_start)(&wk->slack);
  BAL_QX(filter_cold_start)(&wk->filter);
  memset(wk->plan, 0, sizeof(wk->plan));
  wk->plan_age = 0;
  wk->have_plan = wk->have_slack = wk->have_filter = wk->n_replaced = 0;
  wk->slack_status = wk->filter_status = BAL_NOT_RUN;
  wk->h_upper = NAN;
  wk->shift_certified = wk->cert_first = 0;
  wk->h_solver = NAN;
}

/* A failed (2.24): the next input of the last plan, or u_p clipped to U (proposal_fallback
   of balustrade.control.pcbf). */
static int BAL_QX(fallback)(BAL_QX(work)* wk, casadi_real* u_out, int* status) {
  casadi_int i;
  if (wk->have_plan && wk->plan_age + 1 < BAL_QX(N)) {
    wk->plan_age++;
    for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = wk->plan[wk->plan_age * BAL_QX(NU) + i];
    *status = BAL_PCBF_SHIFTED_PLAN;
  } else {
    bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
    *status = BAL_PCBF_PROJECTED;
  }
  return *status;
}

/* (2.23) before its first success: warm start from the variables shared with (2.24)
   (layout offsets src in (2.24), dst in (2.23); stage order through the maps) */
#if BAL_QX(slack_STAGED) || BAL_QX(filter_STAGED)
/* the position of (2.23)'s layout element j in its x */
static casadi_int BAL_QX(f_pos)(casadi_int j) {
#if BAL_QX(filter_STAGED)
  return BAL_QX(f_take)[j];
#else
  return j;
#endif
}
#define BAL_PCBF_COPY_SHARED(src, dst, n) \
  for (i = 0; i < (n); ++i) { \
    wk->filter.x0[BAL_QX(f_pos)((dst) + i)] = BAL_PCBF_SLACK((src) + i); \
  }
#define BAL_PCBF_COPY_SECOND(src, dst, n) \
  for (i = 0; i < (n); ++i) { \
    wk->keep_x0[BAL_QX(f_pos)((dst) + i)] = BAL_PCBF_SLACK((src) + i); \
  }
#else
#define BAL_PCBF_COPY_SHARED(src, dst, n) \
  memcpy(wk->filter.x0 + (dst), wk->slack.x + (src), (n) * sizeof(casadi_real));
#define BAL_PCBF_COPY_SECOND(src, dst, n) \
  memcpy(wk->keep_x0 + (dst), wk->slack.x + (src), (n) * sizeof(casadi_real));
#endif

int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 casadi_real* h_out, int* status, BAL_QX(work)* wk) {
  casadi_int i;
  int certified, trunc_ok, fired = 0, kept = 0;
  if (!x || !u_p || !u_out || !h_out || !status || !wk) {
    if (status) *status = BAL_PCBF_BAD_INPUT;
    return BAL_PCBF_BAD_INPUT;
  }
  wk->slack_status = wk->filter_status = BAL_NOT_RUN;
  wk->h_upper = NAN;
  wk->shift_certified = wk->cert_first = 0;
  wk->h_solver = NAN;
  *h_out = NAN;
  wk->n_replaced = bal_read_proposal(u_p, wk->u_p, BAL_QX(NU));
  if (!bal_finite(x, BAL_QX(NX))) {
    /* nothing is solved with a NaN or inf state (as
       balustrade.control.fallbacks.projected_proposal); the plan is kept */
    wk->slack_status = wk->filter_status = BAL_BAD_INPUT;
    bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
    *status = BAL_PCBF_BAD_INPUT;
    return *status;
  }
#if BAL_QX(SHIFT_CERT) && BAL_QX(CERT_FIRST)
  /* certificate first (PCBFSafetyFilter._first): the shifted plan meets (2.24) with zero
     slack -> h_PB = 0, xi* = 0 (the global optimum, cost 0 forces every slack to 0); (2.24)
     is not solved (its status stays BAL_NOT_RUN), the next one starts from the candidate's
     primal, (2.23) from its usual warm start (with Q_SHIFTED_RETRY a failed attempt from
     its last solution is tried once more from the candidate before the cold retries) */
  if (wk->have_plan && BAL_QX(shift_eval)(wk, x)) {
    wk->cert_first = 1;
    BAL_QX(pcbf_slack_keep)(wk);
    wk->have_slack = 1;
    *h_out = fmax(wk->slack.f, 0.0);
    certified = 1;
    goto filter;
  }
#endif
  /* (2.24): h_PB(x_k) and the slacks xi* */
  for (i = 0; i < BAL_QX(NX); ++i) wk->p_slack[BAL_QX(slack_P_x0) + i] = x[i];
  wk->slack_status = BAL_QX(slack_solve)(&wk->slack, wk->p_slack);
  BAL_QX(pcbf_slack_cost)(wk);
  /* a truncated (2.24) at a feasible iterate (real-time mode) is continued primal-dual by
     the next solve and used as a merely feasible one; stopped infeasible it is a failure */
  trunc_ok = BAL_QX(slack_truncated_feasible)(&wk->slack, wk->slack_status);
  if (trunc_ok) BAL_QX(slack_warm_start)(&wk->slack);
#if BAL_QX(SHIFT_CERT)
  /* the solver's point is not the global optimum h_PB = 0 that the shifted plan attains */
  fired = BAL_QX(shift_check)(wk, x, BAL_SOLVED(wk->slack_status) || trunc_ok);
  wk->shift_certified = fired;
#endif
  if (!fired && !BAL_SOLVED(wk->slack_status) && !trunc_ok) {
    return BAL_QX(fallback)(wk, u_out, status);
  }
  /* only an optimal (2.24) gives h_PB; a feasible point of cost <= ZERO_TOL is optimal
     (h_PB >= 0 is a lower bound it attains), a costlier one only bounds h_PB above */
  certified = fired || wk->slack_status == BAL_OK ||
              fmax(wk->slack.f, 0.0) <= BAL_QX(ZERO_TOL);
  if (certified) {
    if (fired) {
      BAL_QX(pcbf_slack_keep)(wk); /* the candidate has no multipliers */
    } else if (wk->slack_status == BAL_OK) {
      BAL_QX(slack_warm_start)(&wk->slack);
    } else if (!trunc_ok) {
      BAL_QX(pcbf_slack_keep)(wk);
    }
    wk->have_slack = 1;
    *h_out = fmax(wk->slack.f, 0.0);
  } else {
    /* a failed (2.24) (Theorem 2.30 needs its optimum): the shifted plan if any */
    wk->h_upper = fmax(wk->slack.f, 0.0);
    if (wk->have_plan && wk->plan_age + 1 < BAL_QX(N)) return BAL_QX(fallback)(wk, u_out, status);
  }
#if BAL_QX(SHIFT_CERT) && BAL_QX(CERT_FIRST)
filter:
#endif
  /* (2.23) with the slacks fixed: clip slightly negative solver slacks to 0 */
  for (i = 0; i < BAL_QX(NX); ++i) wk->p_filter[BAL_QX(filter_P_x0) + i] = x[i];
  for (i = 0; i < BAL_QX(NU); ++i) wk->p_filter[BAL_QX(filter_P_u_p) + i] = wk->u_p[i];
  for (i = 0; i < BAL_QX(N_XI); ++i) {
    wk->p_filter[BAL_QX(filter_P_xi) + i] = fmax(BAL_PCBF_SLACK(BAL_QX(slack_W_xi) + i), 0.0);
  }
  wk->p_filter[BAL_QX(filter_P_xi_N)] = fmax(BAL_PCBF_SLACK(BAL_QX(slack_W_xi_N)), 0.0);
#if BAL_QX(SHIFT_CERT)
  if (fired && wk->have_filter) { /* kept unless this (2.23) replaces it */
    kept = 1;
    memcpy(wk->keep_x0, wk->filter.x0, sizeof(wk->keep_x0));
    memcpy(wk->keep_lam_x0, wk->filter.lam_x0, sizeof(wk->keep_lam_x0));
    memcpy(wk->keep_lam_g0, wk->filter.lam_g0, sizeof(wk->keep_lam_g0));
  }
#endif
  if (!wk->have_filter || fired) { /* a certified step: from the candidate's states, inputs */
    BAL_QX(filter_cold_start)(&wk->filter);
    BAL_QX(SHARED)(BAL_PCBF_COPY_SHARED)
  }
#if BAL_QX(SHIFT_CERT) && BAL_QX(CERT_FIRST) && BAL_QX(SHIFTED_RETRY)
  if (wk->cert_first && wk->have_filter) {
    /* shifted_retry (opt-in): (2.23) from its last solution; if that attempt fails, from the
       certified shifted plan (feasible for (2.23): PCBFSafetyFilter._filter_solve) before
       the cold retries.
       The plan's start is built as the start of a certified step without a last solution
       (initial values, the variables shared with (2.24)); keep_x0 is free here (fired = 0) */
    memcpy(wk->keep_x0, BAL_QX(filter_init_x), sizeof(wk->keep_x0));
    BAL_QX(SHARED)(BAL_PCBF_COPY_SECOND)
    wk->filter_status = BAL_QX(filter_solve_from)(&wk->filter, wk->p_filter, wk->keep_x0);
  } else
#endif
  wk->filter_status = BAL_QX(filter_solve)(&wk->filter, wk->p_filter);
  trunc_ok = BAL_QX(filter_truncated_feasible)(&wk->filter, wk->filter_status);
#if BAL_QX(SHIFT_CERT)
  if (kept && !(wk->filter_status == BAL_OK || trunc_ok)) {
    memcpy(wk->filter.x0, wk->keep_x0, sizeof(wk->keep_x0));
    memcpy(wk->filter.lam_x0, wk->keep_lam_x0, sizeof(wk->keep_lam_x0));
    memcpy(wk->filter.lam_g0, wk->keep_lam_g0, sizeof(wk->keep_lam_g0));
  }
#else
  (void)kept;
#endif
  if (wk->filter_status == BAL_TRUNCATED && !trunc_ok) {
    wk->have_filter = 0; /* stopped infeasible: the next (2.23) starts from (2.24) */
  }
  if (BAL_SOLVED(wk->filter_status) || trunc_ok) {
    /* a truncated (2.23) at a feasible iterate meets its safety constraints: applied (not
       certified closest to u_p) and continued by the next solve */
    if (wk->filter_status == BAL_OK || trunc_ok) {
      BAL_QX(filter_warm_start)(&wk->filter);
      wk->have_filter = 1;
    }
    for (i = 0; i < BAL_QX(NU) * BAL_QX(N); ++i) {
      wk->plan[i] = BAL_PCBF_FILTER(BAL_QX(filter_W_u) + i);
    }
    *status = BAL_PCBF_OK;
  } else {
    for (i = 0; i < BAL_QX(NU) * BAL_QX(N); ++i) {
      wk->plan[i] = BAL_PCBF_SLACK(BAL_QX(slack_W_u) + i);
    }
    *status = BAL_PCBF_SLACK_SOLUTION;
  }
  if (!certified) *status = BAL_PCBF_FEASIBLE_SLACK;
  wk->plan_age = 0;
  wk->have_plan = 1;
  for (i = 0; i < BAL_QX(NU); ++i) u_out[i] = wk->plan[i];
  return *status;
}

#undef BAL_PCBF_COPY_SHARED
#undef BAL_PCBF_COPY_SECOND

BAL_DEFINE_PAIR_ACCESSORS(BAL_QX, slack, filter, slack_problem, filter_problem)
casadi_real BAL_QX(h_upper)(const BAL_QX(work)* wk) { return wk->h_upper; }
int BAL_QX(shift_certified)(const BAL_QX(work)* wk) { return wk->shift_certified; }
casadi_real BAL_QX(h_solver)(const BAL_QX(work)* wk) { return wk->h_solver; }
int BAL_QX(cert_first)(const BAL_QX(work)* wk) { return wk->cert_first; }
int BAL_QX(proposal_replaced)(const BAL_QX(work)* wk) { return wk->n_replaced; }
