/* bal/approx.h: Algorithm 7.5, the approximate PCBF filter A = BAL_STEP, one call per
 * control step. Included by the generated <name>.h after the problems A_dec (7.6) and
 * A_filter (7.5); A_h and A_h_next (h^(x), h^(f(x, u))) are CasADi-generated.
 *
 * A_step(x, u_p, u_out, h_out, status, work):
 *   1. certification (line 4): if u_p in U and h^(f(x, u_p)) <= 0, apply u_p;
 *   2. else the maximal decrease (7.6) by screened multi-start: evaluate h^(f(x, c)) on the
 *      A_NC candidates {clip(0), clip(u_p), grid over U}, run the local solver of (7.6)
 *      from the A_N_LOCAL best distinct ones, keep the best; dh = h^(x) - min;
 *   3. if u_p in U meets the decrease of (7.5) it is its minimizer (cost 0): apply it
 *      (exact shortcut, BAL_APPROX_PROPOSAL_FEASIBLE; A_EXACT_SHORTCUT = 0 disables it);
 *      else the filter (7.5) with (x, u_p, dh, rho), warm-started at the (7.6) minimizer.
 *   h_out = h^(x_k). With A_NET = 1 (emit_approximate of a filter built with network=) h^ is
 *   evaluated from the network's weights (bal/approx_net.c, the same values) instead of
 *   A_h / A_h_next, and h^(f(x, u_p)) once per step.
 *   Fallbacks, as balustrade.control.approximate:
 *   (7.5) fails or leaves U      -> the (7.6) minimizer       BAL_APPROX_MAX_DECREASE
 *   (7.5) only BAL_FEASIBLE      -> its point (in U, meets the decrease: safe)
 *                                                             BAL_APPROX_FILTER_FEASIBLE
 *   (7.6) finds nothing finite   -> best screened candidate   BAL_APPROX_GRID_MINIMIZER
 *   x NaN/inf, NULL args         -> u_p (NaN -> 0) clipped to U BAL_APPROX_BAD_INPUT
 *   u_p NaN/inf (x finite)       -> those entries read as 0, the step runs as usual
 *                                   (A_proposal_replaced counts them)
 */
#ifndef BAL_STEP
#error "bal/approx.h: define BAL_STEP (the step's symbol prefix) first"
#endif

/* work vectors shared by A_h and A_h_next (and the model A_f when A_NET: h^ is evaluated
   from its network's weights, bal/approx_net.c) */
#if BAL_QX(NET)
#define BAL_APPROX_HSZ(k) \
  BAL_MAX2(BAL_MAX2(BAL_QX(h_SZ_##k), BAL_QX(h_next_SZ_##k)), BAL_QX(f_SZ_##k))
#else
#define BAL_APPROX_HSZ(k) BAL_MAX2(BAL_QX(h_SZ_##k), BAL_QX(h_next_SZ_##k))
#endif

typedef struct BAL_QX(work) {
  BAL_QX(dec_work) dec;
  BAL_QX(filter_work) filter;
  casadi_real p_dec[BAL_QX(dec_NP) + 1], p_filter[BAL_QX(filter_NP) + 1];
  casadi_real cand[BAL_QX(NC) * BAL_QX(NU)], values[BAL_QX(NC)], best_u[BAL_QX(NU)];
  casadi_real u_p[BAL_QX(NU)]; /* the proposal used (non-finite entries replaced by 0) */
  int order[BAL_QX(NC)], tried[BAL_QX(NC)];
  casadi_real h_x, dh, best_v;
  /* h^(f(x, u_p)) of this step, evaluated at most once (certification, screening of
     clip(u_p) when it equals u_p, exact shortcut); h_up_ready = 0 until evaluated */
  casadi_real h_up;
  int h_up_ready;
  const casadi_real* harg[BAL_APPROX_HSZ(ARG)];
  casadi_real* hres[BAL_APPROX_HSZ(RES)];
  casadi_int hiw[BAL_APPROX_HSZ(IW) + 1];
  casadi_real hw[BAL_APPROX_HSZ(W) + 1];
  int hmem, nmem, fmem; /* fmem: A_f's memory (A_NET only) */
  int dec_status, filter_status, certify, ready, n_replaced;
  long n_steps, n_certified, n_solved, n_fallbacks, n_proposal_feasible;
} BAL_QX(work);

/* reset: zero the counters */
BAL_DECLARE_STEP_LIFECYCLE(BAL_QX)
int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 casadi_real* h_out, int* status, BAL_QX(work)* wk);
void BAL_QX(set_certify)(BAL_QX(work)* wk, int certify); /* 0: always solve (7.6), (7.5) */
casadi_real BAL_QX(dh)(const BAL_QX(work)* wk); /* dh of the last solved step (NAN if none) */
/* 1 if the last step's (7.5) returned BAL_OK at its solver's acceptable level
   (<P>_inaccurate: the backend's optimal_inaccurate; applied, flagged), else 0 */
int BAL_QX(inaccurate)(const BAL_QX(work)* wk);
/* which: 0 steps, 1 certified, 2 solved, 3 fallbacks, 4 proposal feasible */
long BAL_QX(counter)(const BAL_QX(work)* wk, int which);
