/* bal/robust.h: the Algorithm 5.2 control step Q = BAL_STEP: (5.15) then (5.16), one call
 * per step. Included by the generated <name>.h after the problems Q_slack (5.15) and
 * Q_filter (5.16).
 *
 * Q_step(x, u_p, u_out, h_out, status, work):
 *   x      measured state x_k              (Q_NX values, read)
 *   u_p    proposed input u_{p,k}          (Q_NU values, read)
 *   u_out  input to apply u_k              (Q_NU values, written)
 *   h_out  h_r(x_k) = h~ of the polished slacks of (5.15) (not its optimum: see robust.py)
 *          (NAN if (5.15) did not converge)
 *   status BAL_ROBUST_* (also returned)
 * Per step, as balustrade.control.robust.RobustPCBFSafetyFilter:
 *   h_cand := h~ of the candidate (5.17) built at the previous step (Q_h_cand; NAN if none);
 *   solve (5.15) warm-started from its last converged solution; polish its slacks
 *   (Q_post: elementwise min with the slacks its z needs) and fix them in (5.16); solve
 *   (5.16) warm-started from its last converged solution (the first time from z, v of
 *   (5.15)); apply u = v_0 + K(x - z_0) of the chosen optimizer and build the next
 *   candidate (5.17) from it (Q_cand). Fallbacks:
 *   (5.16) not BAL_OK              -> the (5.15) optimizer        BAL_ROBUST_SLACK_SOLUTION
 *   (5.15) not BAL_OK              -> the last candidate, shifted BAL_ROBUST_CANDIDATE
 *   no candidate                   -> u_p clipped to U            BAL_ROBUST_PROJECTED
 *   x NaN/inf, NULL args           -> u_p (NaN -> 0) clipped to U BAL_ROBUST_BAD_INPUT
 *   u_p NaN/inf (x finite)         -> those entries read as 0, the step runs as usual
 * The candidate's terminal input is pi_f(z_N) when it lies in U - K E; otherwise the
 * largest decrease of h_f over U - K E, which Q_cand computes exactly only for one input
 * with h_f(f(z_N, v, 0)) quadratic in v (Q_CAND_EXACT_OUTSIDE); else no candidate is kept
 * (Q_candidate_exact returns 0 after such a step).
 */
#ifndef BAL_STEP
#error "bal/robust.h: define BAL_STEP (the step's symbol prefix) first"
#endif

typedef struct BAL_QX(work) {
  BAL_QX(slack_work) slack;
  BAL_QX(filter_work) filter;
  casadi_real p_slack[BAL_QX(slack_NP) + 1], p_filter[BAL_QX(filter_NP) + 1];
  /* the candidate (5.17) for the next step, and the next one while it is built */
  BAL_TUBE_CANDIDATE_MEMBERS(BAL_QX)
  /* the polished slacks of (5.15) and h_r */
  casadi_real xi[BAL_QX(N_XI)], xi_N, h_r;
  casadi_real u_p[BAL_QX(NU)]; /* the proposal used (non-finite entries replaced by 0) */
  casadi_real h_cand;          /* h~ of the candidate at the start of the step, else NAN */
  /* CasADi work vectors of Q_post and Q_cand */
  const casadi_real* arg[BAL_QX(SZ_ARG)];
  casadi_real* res[BAL_QX(SZ_RES)];
  casadi_int iw[BAL_QX(SZ_IW) + 1];
  casadi_real w[BAL_QX(SZ_W) + 1];
  int have_cand, cand_exact, have_slack, have_filter, n_replaced;
  int recovered; /* the last converged (5.15) was a recovery solve: the next starts from the candidate */
  /* the start of the last converged (5.15) while slack.x0 holds the candidate's: restored
     after that solve, so that a later (5.15) without a candidate starts from it (Python's
     _last_slack) and not from a stale candidate */
  casadi_real kx0[BAL_QX(slack_NW)], klam_x0[BAL_QX(slack_NW)], klam_g0[BAL_QX(slack_NG) + 1];
  int slack_status, filter_status; /* BAL_* of the last step's solves */
  int ready;
} BAL_QX(work);

/* reset: forget warm starts and the candidate (a new closed loop) */
BAL_DECLARE_STEP_LIFECYCLE(BAL_QX)
int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 casadi_real* h_out, int* status, BAL_QX(work)* wk);
/* solve_status which: 0 (5.15), 1 (5.16) */
BAL_DECLARE_PAIR_ACCESSORS(BAL_QX, slack, filter, slack_problem, filter_problem)
/* h~ of the candidate (5.17) at the start of the last step (NAN if there was none). */
casadi_real BAL_QX(h_cand)(const BAL_QX(work)* wk);
/* 0 if the last candidate built needed a terminal input the C cannot compute (dropped). */
int BAL_QX(candidate_exact)(const BAL_QX(work)* wk);
