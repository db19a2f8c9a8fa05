/* bal/pcbf.h: the PCBF control step Q = BAL_STEP: (2.24) then (2.23), one call per step.
 * Included by the generated <name>.h after the problems Q_slack (2.24) and Q_filter (2.23).
 *
 * Q_step(x, u_p, u_out, h_out, status, work):
 *   x      measured state x_k              (Q_NX values, read)
 *   u_p    proposed input u_{p,k}          (Q_NU values, read)
 *   u_out  input to apply u_k              (Q_NU values, written)
 *   h_out  h_PB(x_k) = max(optimum of (2.24), 0) (NAN if (2.24) was not solved to
 *          optimality: see Q_h_upper)
 *   status BAL_PCBF_* (also returned)
 * Per step: solve (2.24) warm-started from its last converged solution; clip its slacks
 * at 0 and fix them (plus eps, built into the problem) as parameters of (2.23); solve
 * (2.23) warm-started from its last converged solution (the first time: from the states and
 * inputs of (2.24)); apply u*_{0|k}. Fallbacks, as balustrade.control.pcbf:
 *   (2.23) fails                 -> u_{0|k} of (2.24)              BAL_PCBF_SLACK_SOLUTION
 *   (2.24) fails                 -> next input of the last plan    BAL_PCBF_SHIFTED_PLAN
 *   no plan left                 -> u_p clipped to U               BAL_PCBF_PROJECTED
 *   (2.24) BAL_FEASIBLE, cost > Q_ZERO_TOL (not converged: its cost only bounds h_PB
 *          from above; h_out NAN, Q_h_upper the bound) -> a failed (2.24): the shifted
 *          plan; no plan left -> (2.23) on its slacks          BAL_PCBF_FEASIBLE_SLACK
 *          (a BAL_FEASIBLE point of cost <= Q_ZERO_TOL is optimal: h_PB >= 0)
 *   a solve stopped by its iteration budget (BAL_TRUNCATED, real-time mode): at a
 *          feasible iterate (residual <= P_TRUNC_TOL) (2.24) is used as a BAL_FEASIBLE one
 *          and (2.23) is applied, both continued primal-dual by the next step's solve;
 *          stopped infeasible, it is a failed solve (a failed (2.23) restarts from (2.24))
 *   x NaN/inf, NULL args         -> u_p (NaN -> 0) clipped to U    BAL_PCBF_BAD_INPUT
 *                                   (nothing solved; both solve statuses BAL_BAD_INPUT)
 *   u_p NaN/inf (x finite)       -> those entries of u_p read as 0, the step runs as usual
 *                                   (Q_proposal_replaced counts them)
 * Shifted-plan certificate (Q_SHIFT_CERT = 1, balustrade.control.shifted): when (2.24)
 * fails or its cost exceeds max(Q_ZERO_TOL, Q_EPS) and a plan exists, the remaining inputs
 * of the last plan (then zeros) are rolled out from x by the emitted Q_shift_cert (the
 * function the Python certificate evaluates); if the candidate violates no row or bound of
 * (2.24) by more than Q_CERT_TOL and its cost is <= Q_ZERO_TOL, it replaces the solver's
 * point: h_PB = 0 (lower bound), (2.24) is warm-started from its primal and (2.23) from its
 * states and inputs (Q_shift_certified = 1, Q_h_solver the solver's cost or NAN).
 * Certificate first (Q_CERT_FIRST = 1, needs Q_SHIFT_CERT; PCBFSafetyFilter's
 * certificate_first, on by default wherever the certificate is emitted): with a plan, the same candidate is checked BEFORE (2.24); if it
 * qualifies, (2.24) is not solved (Q_solve_status 0 stays BAL_NOT_RUN): h_PB = 0, xi* = 0
 * ((2.24)'s cost is 0 only with every slack 0), (2.23) runs from its usual warm start, the
 * next (2.24) starts from the candidate's primal (Q_cert_first = 1; status BAL_PCBF_OK or a
 * (2.23) fallback as usual). With Q_SHIFTED_RETRY = 1 (PCBFSafetyFilter's shifted_retry,
 * opt-in, off by default) a failed (2.23) attempt from its last solution in such a step is
 * run once more from the candidate before the cold retries (Q_filter_solve_from).
 * Warm starts as balustrade's backend: from a converged solution (primal and multipliers);
 * from the primal of a certified BAL_FEASIBLE (2.24) (zero multipliers); never from an
 * uncertified one; (2.23) only from BAL_OK solutions.
 * The solutions stay in work->slack / work->filter (x: full primal, f: optimum).
 * A problem compiled in stage order (Q_slack_STAGED / Q_filter_STAGED, the structured-ip targets,
 * issue #14): its x, warm start and multipliers are in the solver's stage order; the step
 * reads layout element i as x[P_TAKE[i]] projected onto the layout's bounds (as the
 * backend's StageInverse.primal and its projection), writes warm starts by the same map,
 * and takes h_PB from Q_slack_obj, the declared cost at that projected point (the
 * solver's own value reads the interior-point solver's ~1e-8 bound relaxation times the slack weights).
 */
#ifndef BAL_STEP
#error "bal/pcbf.h: define BAL_STEP (the step's symbol prefix) first"
#endif

typedef struct BAL_QX(work) {
  BAL_QX(slack_work) slack;
  BAL_QX(filter_work) filter;
  casadi_real p_slack[BAL_QX(slack_NP) + 1], p_filter[BAL_QX(filter_NP) + 1];
  casadi_real plan[BAL_QX(NU) * BAL_QX(N)];
  casadi_real u_p[BAL_QX(NU)]; /* the proposal used (non-finite entries replaced by 0) */
  casadi_real h_upper;         /* cost of an uncertified BAL_FEASIBLE (2.24), else NAN */
  int plan_age, have_plan, have_slack, have_filter, n_replaced;
  int slack_status, filter_status; /* BAL_* of the last step's solves */
  int shift_certified;             /* the last step used the shifted-plan certificate */
  int cert_first;                  /* the last step skipped (2.24): certificate first */
  casadi_real h_solver;            /* then: the solver's (2.24) cost (NAN if not usable) */
#if BAL_QX(slack_STAGED)
  /* (2.24) in stage order: its layout point (projected) and the work of Q_slack_obj */
  casadi_real s_lay[BAL_QX(slack_NW)];
  const casadi_real* oarg[BAL_QX(slack_obj_SZ_ARG)];
  casadi_real* ores[BAL_QX(slack_obj_SZ_RES)];
  casadi_int oiw[BAL_QX(slack_obj_SZ_IW) + 1];
  casadi_real ow[BAL_QX(slack_obj_SZ_W) + 1];
#endif
#if BAL_QX(SHIFT_CERT)
  casadi_real cert_U[BAL_QX(NU) * BAL_QX(N)], cert_w[BAL_QX(slack_N_USER) + 1];
  casadi_real cert_v, cert_f;
  /* the warm start of (2.23), kept while a certified step starts it from the candidate;
     with Q_SHIFTED_RETRY, in a certificate-first step keep_x0 is (2.23)'s second start */
  casadi_real keep_x0[BAL_QX(filter_NW)], keep_lam_x0[BAL_QX(filter_NW)];
  casadi_real keep_lam_g0[BAL_QX(filter_NG) + 1];
  const casadi_real* carg[BAL_QX(shift_cert_SZ_ARG)];
  casadi_real* cres[BAL_QX(shift_cert_SZ_RES)];
  casadi_int ciw[BAL_QX(shift_cert_SZ_IW) + 1];
  casadi_real cw[BAL_QX(shift_cert_SZ_W) + 1];
  int cmem;
#endif
  int ready;
} BAL_QX(work);

/* reset: forget warm starts and the plan (a new closed loop) */
BAL_DECLARE_STEP_LIFECYCLE(BAL_QX)
int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 casadi_real* h_out, int* status, BAL_QX(work)* wk);
/* solve_status which: 0 (2.24), 1 (2.23) */
BAL_DECLARE_PAIR_ACCESSORS(BAL_QX, slack, filter, slack_problem, filter_problem)
/* The last step's upper bound on h_PB from a merely feasible (2.24) (NAN if none). */
casadi_real BAL_QX(h_upper)(const BAL_QX(work)* wk);
/* 1 if the last step used the shifted-plan certificate as its (2.24) point, else 0. */
int BAL_QX(shift_certified)(const BAL_QX(work)* wk);
/* The solver's (2.24) cost at a certified step (NAN if it was not usable or no step). */
casadi_real BAL_QX(h_solver)(const BAL_QX(work)* wk);
/* 1 if the last step skipped (2.24) on the certificate (Q_CERT_FIRST), else 0. */
int BAL_QX(cert_first)(const BAL_QX(work)* wk);
