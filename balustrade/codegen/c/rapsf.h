/* bal/rapsf.h: the Algorithm 4.1 control step Q = BAL_STEP (the robust adaptive predictive
 * safety filter with homothetic tubes, thesis Chapter 4, SPEC §2.21), one call per step.
 * Included by the generated <name>.h after the problem Q_main, the QP (4.5) with the
 * vertices of Theta_k (theta) and the support constants s_jr (s) as parameters, and, with
 * Q_SHRINKING (Remark 4.6), the problems Q_shrunk<h>: (4.5) with the horizon h = 1 ... N-1
 * and the same parameters (listed by the X-macro Q_SHRUNK of <name>_config.h).
 *
 * Q_step(x, u_p, theta, s, falsified, u_out, status, work):
 *   x         measured state x_k                          (Q_NX values, read)
 *   u_p       proposed input u_{p,k}                      (Q_NU values, read)
 *   theta     the vertices of Theta_k as columns          (Q_NQ x Q_NTH, column-major)
 *   s         s_jr of SPEC §2.20 for those vertices       (Q_NXR x Q_NTH, column-major)
 *             (fewer vertices than Q_NTH: repeat them; the caller computes Theta_k with
 *             its set-membership estimator and s from it, both stay in the host language)
 *   falsified nonzero when the estimator excluded every model in Theta
 *   u_out     input to apply u_k                           (Q_NU values, written)
 *   status    BAL_RAPSF_* (also returned)
 * Per step, as balustrade.control.rapsf.RAPSF:
 *   solve (4.5) at (x, Theta_k) from a cold start (the retries of bal/problem.c);
 *   BAL_OK -> u = K x + v*_0, store the plan v*, k_inf := 0        BAL_RAPSF_OK
 *   (a BAL_OK at the solver's acceptable level, Q_inaccurate, counts as failed: RAPSF uses
 *   only optimal solves)
 *   else k_inf := k_inf + 1 and
 *     k_inf <= N - 1 and a stored plan, Q_SHRINKING (Remark 4.6): solve (4.5) with the
 *       horizon N - k_inf (cold start); BAL_OK -> u = K x + v^_0 of that solve, and
 *       v^ becomes the stored plan from stage k_inf on (k_inf keeps counting)
 *                                                                  BAL_RAPSF_SHRUNK_HORIZON
 *     k_inf <= N - 1 and a stored plan -> u = K x + v*_{k_inf}    BAL_RAPSF_STORED_PLAN
 *     otherwise the backup policy u = pi_Cf(x)                     BAL_RAPSF_BACKUP
 *   falsified                       -> u = pi_Cf(x), nothing solved  BAL_RAPSF_FALSIFIED
 *   x NaN/inf, NULL args            -> u = pi_Cf(x) (NaN entries of x as 0) BAL_RAPSF_BAD_INPUT
 * pi_Cf by Q_BACKUP: 0 the default K x, 1 the affine law K_b x + k_b (Q_KB, Q_KB0), 2 the
 * emitted CasADi function Q_backup_policy(x) (NaN outputs if it fails or work is NULL).
 *   u_p NaN/inf (x finite)          -> those entries read as 0, the step runs as usual
 * k_inf starts at N - 1 (Q_reset): without a stored plan a failed solve uses the backup.
 */
#ifndef BAL_STEP
#error "bal/rapsf.h: define BAL_STEP (the step's symbol prefix) first"
#endif

typedef struct BAL_QX(work) {
  BAL_QX(main_work) main;
#define BAL_RAPSF_SHRUNK_MEMBER(tag, h) BAL_QX(tag##_work) tag;
  BAL_QX(SHRUNK)(BAL_RAPSF_SHRUNK_MEMBER) /* (4.5) with the horizon h (Q_SHRINKING) */
#undef BAL_RAPSF_SHRUNK_MEMBER
  casadi_real p[BAL_QX(main_NP) + 1];
  casadi_real plan[BAL_QX(NU) * BAL_QX(N)]; /* v* of the last converged (4.5), NU x N;
                                               from k_inf on v^ of a converged shrunk solve */
  casadi_real u_p[BAL_QX(NU)];              /* the proposal used (non-finite -> 0) */
  casadi_real objective;                    /* of the last converged (4.5), else NAN */
  int have_plan, k_inf, main_status, shrunk_status, n_replaced, ready;
  int main_inaccurate, shrunk_inaccurate; /* that solve's BAL_OK stopped at the acceptable level */
#if BAL_QX(BACKUP) == 2
  /* the backup policy Q_backup_policy(x): its arguments, work and memory */
  const casadi_real* barg[BAL_QX(backup_policy_SZ_ARG)];
  casadi_real* bres[BAL_QX(backup_policy_SZ_RES)];
  casadi_int biw[BAL_QX(backup_policy_SZ_IW) + 1];
  casadi_real bw[BAL_QX(backup_policy_SZ_W) + 1];
  casadi_real bx[BAL_QX(NX)];
  int bmem;
#endif
} BAL_QX(work);

/* reset: forget the stored plan, k_inf := N - 1 (a new closed loop) */
BAL_DECLARE_STEP_LIFECYCLE(BAL_QX)
int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, const casadi_real* theta,
                 const casadi_real* s, int falsified, casadi_real* u_out, int* status,
                 BAL_QX(work)* wk);
/* the problem (4.5) inside the work struct, for foreign-function callers */
BAL_QX(main_work)* BAL_QX(main_problem)(BAL_QX(work)* wk);
/* BAL_* status of the last step's (4.5) solve (BAL_NOT_RUN if none ran; a BAL_OK with
   Q_inaccurate 1 was not used) */
int BAL_QX(solve_status)(const BAL_QX(work)* wk);
/* BAL_* status of the last step's shrunk-horizon solve (BAL_NOT_RUN if none ran) */
int BAL_QX(shrunk_status)(const BAL_QX(work)* wk);
/* 1 if the last step's (4.5) (which 0) or shrunk-horizon solve (which 1) returned BAL_OK at
   the solver's acceptable level (<P>_inaccurate: the backend's optimal_inaccurate), which the
   step, as RAPSF, did not use (handled as a failed solve); else 0 */
int BAL_QX(inaccurate)(const BAL_QX(work)* wk, int which);
/* k_inf after the last step */
int BAL_QX(k_inf)(const BAL_QX(work)* wk);
/* objective of the last step's (4.5) if it converged, else NAN */
casadi_real BAL_QX(objective)(const BAL_QX(work)* wk);
