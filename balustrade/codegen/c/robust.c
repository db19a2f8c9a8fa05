/* bal/robust.c: the Algorithm 5.2 control step Q = BAL_STEP ((5.15) then (5.16),
 * bal/robust.h) with the fallbacks of balustrade.control.robust. Included by the generated
 * <name>.c after the problems Q_slack and Q_filter. From <name>_config.h: Q_NX, Q_NU, Q_N,
 * Q_N_XI, the box U (Q_U_LB, Q_U_UB), the feedback Q_K (NU x NX, column-major), the sizes
 * Q_SZ_* of the emitted functions Q_post (polished slacks and h_r) and Q_cand (the
 * candidate (5.17)), and the offsets of the problems (Q_slack_W_z, ...).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "step_common.c"

static const casadi_real BAL_QX(u_lb)[BAL_QX(NU)] = BAL_QX(U_LB);
static const casadi_real BAL_QX(u_ub)[BAL_QX(NU)] = BAL_QX(U_UB);
static const casadi_real BAL_QX(kappa)[BAL_QX(NU) * BAL_QX(NX)] = BAL_QX(K);

BAL_DEFINE_PAIR_INIT_FINALIZE(BAL_QX, slack, filter)

BAL_DEFINE_ALLOC_FREE(BAL_QX)

#include "tube_common.c"

void BAL_QX(reset)(BAL_QX(work)* wk) {
  BAL_QX(slack_cold_start)(&wk->slack);
  BAL_QX(filter_cold_start)(&wk->filter);
  wk->have_cand = wk->have_slack = wk->have_filter = wk->n_replaced = wk->recovered = 0;
  wk->cand_exact = 1;
  wk->slack_status = wk->filter_status = BAL_NOT_RUN;
  wk->h_cand = wk->h_r = NAN;
}

/* A failed (5.15): the last candidate (then shifted again), or u_p clipped to U. */
static int BAL_QX(fallback)(BAL_QX(work)* wk, const casadi_real* x, casadi_real* u_out,
                            int* status) {
  if (wk->have_cand) {
    BAL_QX(applied)(x, wk->cz, wk->cv, u_out);
    BAL_QX(make_candidate)(wk, wk->cz, wk->cv, wk->cxi);
    *status = BAL_ROBUST_CANDIDATE;
  } else {
    bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
    *status = BAL_ROBUST_PROJECTED;
  }
  return *status;
}

int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 casadi_real* h_out, int* status, BAL_QX(work)* wk) {
  casadi_int i;
  int lead, from_cand;
  const casadi_real *z, *v;
  if (!x || !u_p || !u_out || !h_out || !status || !wk) {
    if (status) *status = BAL_ROBUST_BAD_INPUT;
    return BAL_ROBUST_BAD_INPUT;
  }
  wk->slack_status = wk->filter_status = BAL_NOT_RUN;
  wk->h_r = *h_out = NAN;
  wk->h_cand = NAN;
  wk->n_replaced = bal_read_proposal(u_p, wk->u_p, BAL_QX(NU));
  if (!bal_finite(x, BAL_QX(NX))) {
    /* nothing solved (balustrade.control.fallbacks.projected_proposal); candidate kept */
    wk->slack_status = wk->filter_status = BAL_BAD_INPUT;
    bal_clip(wk->u_p, BAL_QX(u_lb), BAL_QX(u_ub), u_out, BAL_QX(NU));
    *status = BAL_ROBUST_BAD_INPUT;
    return *status;
  }
  if (wk->have_cand) wk->h_cand = wk->ch;
  /* a recovery step (the first step, or a candidate whose h~ is positive: it does not
     certify h_r(x_k) = 0) runs the attempt Q_SLACK_LEAD of the (5.15) chain first
     (balustrade.control.robust.RobustPCBFSafetyFilter.recovering; 0: none) */
  lead = (BAL_QX(SLACK_LEAD) > 0 && (!wk->have_cand || wk->ch > 0.0)) ? BAL_QX(SLACK_LEAD) : 0;
  from_cand = wk->recovered && wk->have_cand;
  if (from_cand) {
    /* the last converged (5.15) was a recovery solve: from the candidate, the rest cold;
       the start of the last converged (5.15) is kept aside (restored below) */
    memcpy(wk->kx0, wk->slack.x0, sizeof(wk->kx0));
    memcpy(wk->klam_x0, wk->slack.lam_x0, sizeof(wk->klam_x0));
    memcpy(wk->klam_g0, wk->slack.lam_g0, sizeof(wk->klam_g0));
    BAL_QX(slack_cold_start)(&wk->slack);
    memcpy(wk->slack.x0 + BAL_QX(slack_W_z), wk->cz, sizeof(wk->cz));
    memcpy(wk->slack.x0 + BAL_QX(slack_W_v), wk->cv, sizeof(wk->cv));
    memcpy(wk->slack.x0 + BAL_QX(slack_W_xi), wk->cxi, sizeof(wk->cxi));
    wk->slack.x0[BAL_QX(slack_W_xi_N)] = wk->cxi_N;
  }
  /* (5.15): h_r(x_k) and the slacks */
  for (i = 0; i < BAL_QX(NX); ++i) wk->p_slack[BAL_QX(slack_P_x0) + i] = x[i];
  wk->slack_status = BAL_QX(slack_solve_lead)(&wk->slack, wk->p_slack, 0, lead);
  if (from_cand) {
    /* the candidate was this solve's start only: the start stays the last converged
       (5.15) until a (5.15) is kept below (slack_warm_start), as robust.py, whose warm start
       is the candidate only while there is one, else _last_slack */
    memcpy(wk->slack.x0, wk->kx0, sizeof(wk->kx0));
    memcpy(wk->slack.lam_x0, wk->klam_x0, sizeof(wk->klam_x0));
    memcpy(wk->slack.lam_g0, wk->klam_g0, sizeof(wk->klam_g0));
  }
  if (wk->slack_status != BAL_OK) {
    /* a truncated (5.15) at a feasible iterate (real-time mode) is continued primal-dual
       by the next solve; its cost only bounds h_r (balustrade.control.robust) */
    if (BAL_QX(slack_truncated_feasible)(&wk->slack, wk->slack_status)) {
      BAL_QX(slack_warm_start)(&wk->slack);
    }
    return BAL_QX(fallback)(wk, x, u_out, status);
  }
  /* polished slacks and h_r (Q_post) */
  wk->arg[0] = wk->slack.x;
  wk->arg[1] = &wk->slack.f;
  wk->res[0] = wk->xi;
  wk->res[1] = &wk->xi_N;
  wk->res[2] = &wk->h_r;
  wk->res[3] = 0; /* h~ of the polished slacks: not needed here */
  if (BAL_QX(post)(wk->arg, wk->res, wk->iw, wk->w, 0)) {
    BAL_QX(slack_warm_start)(&wk->slack);
    wk->have_slack = 1;
    wk->slack_status = BAL_EVAL_ERROR;
    wk->h_r = NAN;
    return BAL_QX(fallback)(wk, x, u_out, status);
  }
  *h_out = wk->h_r;
  /* converged above the candidate's h~: a worse local solution, a failed (5.15) whose
     point does not warm-start the next one (balustrade.control.robust) */
  if (wk->have_cand &&
      wk->h_r > wk->ch + BAL_QX(ABOVE_CAND_TOL) * (1.0 + wk->ch)) {
    BAL_QX(fallback)(wk, x, u_out, status);
    *status = BAL_ROBUST_ABOVE_CANDIDATE;
    return *status;
  }
  BAL_QX(slack_warm_start)(&wk->slack);
  wk->have_slack = 1;
  wk->recovered = lead > 0;
  /* (5.16) with the polished slacks fixed */
  for (i = 0; i < BAL_QX(NX); ++i) wk->p_filter[BAL_QX(filter_P_x0) + i] = x[i];
  for (i = 0; i < BAL_QX(NU); ++i) wk->p_filter[BAL_QX(filter_P_u_p) + i] = wk->u_p[i];
  for (i = 0; i < BAL_QX(N_XI); ++i) wk->p_filter[BAL_QX(filter_P_xi) + i] = wk->xi[i];
  wk->p_filter[BAL_QX(filter_P_xi_N)] = wk->xi_N;
  if (!wk->have_filter || lead) {
    /* before its first success and on a recovery step: z, v of (5.15), the rest cold */
    BAL_QX(filter_cold_start)(&wk->filter);
    memcpy(wk->filter.x0 + BAL_QX(filter_W_z), wk->slack.x + BAL_QX(slack_W_z),
           BAL_QX(NX) * (BAL_QX(N) + 1) * sizeof(casadi_real));
    memcpy(wk->filter.x0 + BAL_QX(filter_W_v), wk->slack.x + BAL_QX(slack_W_v),
           BAL_QX(NU) * BAL_QX(N) * sizeof(casadi_real));
  }
  /* no candidate (the first step): the attempt Q_FILTER_LEAD leads (5.16), as
     RobustPCBFSafetyFilter.filter_lead (0: none) */
  wk->filter_status = BAL_QX(filter_solve_lead)(&wk->filter, wk->p_filter, 0,
                                                wk->have_cand ? 0 : BAL_QX(FILTER_LEAD));
  if (wk->filter_status == BAL_TRUNCATED &&
      !BAL_QX(filter_truncated_feasible)(&wk->filter, wk->filter_status)) {
    wk->have_filter = 0; /* stopped infeasible: the next (5.16) starts from (5.15) */
  }
  /* a truncated (5.16) at a feasible iterate meets the tube constraints: applied (not
     certified closest to u_p) and continued by the next solve */
  if (wk->filter_status == BAL_OK ||
      BAL_QX(filter_truncated_feasible)(&wk->filter, wk->filter_status)) {
    BAL_QX(filter_warm_start)(&wk->filter);
    wk->have_filter = 1;
    z = wk->filter.x + BAL_QX(filter_W_z);
    v = wk->filter.x + BAL_QX(filter_W_v);
    *status = BAL_ROBUST_OK;
  } else {
    z = wk->slack.x + BAL_QX(slack_W_z);
    v = wk->slack.x + BAL_QX(slack_W_v);
    *status = BAL_ROBUST_SLACK_SOLUTION;
  }
  BAL_QX(applied)(x, z, v, u_out);
  BAL_QX(make_candidate)(wk, z, v, wk->xi);
  return *status;
}

BAL_DEFINE_PAIR_ACCESSORS(BAL_QX, slack, filter, slack_problem, filter_problem)
casadi_real BAL_QX(h_cand)(const BAL_QX(work)* wk) { return wk->h_cand; }
int BAL_QX(proposal_replaced)(const BAL_QX(work)* wk) { return wk->n_replaced; }
int BAL_QX(candidate_exact)(const BAL_QX(work)* wk) { return wk->cand_exact; }
