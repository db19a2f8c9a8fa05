/* bal/multiobj.h: the Algorithm 6.4 control step Q = BAL_STEP (multiobjective robust
 * PCBF), one call per step. Included by the generated <name>.h after the problems Q_slack
 * (5.15) and Q_problem (6.15).
 *
 * Q_step(x, u_p, u_out, status, work):
 *   x      measured state x_k              (Q_NX values, read)
 *   u_p    proposed input u_{p,k}          (Q_NU values, read)
 *   u_out  input to apply u_k              (Q_NU values, written)
 *   status BAL_MULTIOBJ_* (also returned)
 * Per step, as balustrade.control.multiobjective.MultiobjectivePCBFController:
 *   no candidate: solve (5.15) (warm-started from its last converged solution); the
 *     candidate := (z, v, polished slacks) of it, h_prev := h~ of those slacks; if (5.15)
 *     fails: u_p clipped to U                                   BAL_MULTIOBJ_INIT_FAILED
 *   bound := (1 - rho) h~(candidate) + rho h_prev, plus Q_BOUND_TOL max(1, |bound|) (6.15g);
 *   solve (6.15) warm-started from its last converged solution (else from the candidate);
 *   converged: (z, v, polished slacks) of it                    BAL_MULTIOBJ_OK
 *   converged, but h~ of its polished slacks above the bound by more than
 *     Q_DECREASE_TOL max(1, |bound|) (no feasible point): the candidate
 *                                                               BAL_MULTIOBJ_ABOVE_BOUND
 *   else: the candidate                                         BAL_MULTIOBJ_WARM_START
 *   h_prev := h~ of the chosen slacks; the next candidate (6.14) from the chosen point;
 *   apply u = v_0 + K(x - z_0).
 *   x NaN/inf, NULL args -> u_p (NaN -> 0) clipped to U         BAL_MULTIOBJ_BAD_INPUT
 *   u_p NaN/inf (x finite) -> those entries read as 0, the step runs as usual
 * Q_values(work, out): out[0] = h_cand, out[1] = bound, out[2] = h_tilde of the last step,
 * out[3] = h~ of a converged (6.15) rejected above the bound (BAL_MULTIOBJ_ABOVE_BOUND)
 * (NAN where not computed). The candidate's terminal input as in bal/robust.h
 * (Q_candidate_exact); a dropped candidate makes the next step start again from (5.15).
 */
#ifndef BAL_STEP
#error "bal/multiobj.h: define BAL_STEP (the step's symbol prefix) first"
#endif

typedef struct BAL_QX(work) {
  BAL_QX(slack_work) slack;
  BAL_QX(problem_work) problem;
  casadi_real p_slack[BAL_QX(slack_NP) + 1], p_problem[BAL_QX(problem_NP) + 1];
  /* the candidate (6.14), and the next one while it is built */
  BAL_TUBE_CANDIDATE_MEMBERS(BAL_QX)
  /* polished slacks of the last solve and their h~ */
  casadi_real xi[BAL_QX(N_XI)], xi_N, h_r, h_tilde;
  casadi_real h_prev;              /* h~(xi*_{k-1}) */
  casadi_real cstart[BAL_QX(problem_NW)]; /* the candidate as a second start of (6.15) */
  casadi_real values[4];           /* h_cand, bound, h_tilde, h_tilde_rejected */
  casadi_real u_p[BAL_QX(NU)];
  const casadi_real* arg[BAL_QX(SZ_ARG)];
  casadi_real* res[BAL_QX(SZ_RES)];
  casadi_int iw[BAL_QX(SZ_IW) + 1];
  casadi_real w[BAL_QX(SZ_W) + 1];
  int have_cand, cand_exact, have_problem, n_replaced;
  int recovered; /* no (6.15) converged since a recovery solve (the next starts from the candidate) */
  int slack_status, problem_status; /* BAL_* of the last step's solves */
  int ready;
} BAL_QX(work);

/* reset: forget warm starts and the candidate (a new closed loop) */
BAL_DECLARE_STEP_LIFECYCLE(BAL_QX)
int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 int* status, BAL_QX(work)* wk);
/* solve_status which: 0 (5.15), 1 (6.15) */
BAL_DECLARE_PAIR_ACCESSORS(BAL_QX, slack, problem, slack_problem, main_problem)
void BAL_QX(values)(const BAL_QX(work)* wk, casadi_real* out);
int BAL_QX(candidate_exact)(const BAL_QX(work)* wk);
