/* bal/multiobj_lyap.h: the Algorithm 6.3 control step Q = BAL_STEP (the multiobjective
 * Lyapunov controller of the linear design (6.10), thesis Section 6.3.2), one call per step.
 * Included by the generated <name>.h after the problems Q_first, (6.3) without (6.3h)
 * (parameters x0, u_p), and Q_problem, (6.10) (parameters x0, u_p, bound).
 *
 * Q_step(x, u_p, u_out, status, work):
 *   x      measured state x_k              (Q_NX values, read)
 *   u_p    proposed input u_{p,k}          (Q_NU values, read)
 *   u_out  input to apply u_k              (Q_NU values, written)
 *   status BAL_MO_LYAP_* (also returned)
 * Per step, as balustrade.control.multiobjective.MultiobjectiveLyapunovController:
 *   first step: solve (6.3) without (6.3h) from a cold start; u~ := its v; if it fails:
 *     u_p clipped to U (the next step starts again)           BAL_MO_LYAP_INIT_FAILED
 *   later steps: w := x - A x_prev - B u_prev, u~ := xi_f (6.12) if x in X_f,
 *     V(xi_f) <= V(xi_c) and xi_f meets (6.3b-g), else xi_c (6.11) (switching rule
 *     (6.6)/(6.7), the numbers from Q_switch);
 *   bound := V((x, u~)) - (1 - rho) l(x, u~_0) plus Q_BOUND_TOL max(1, |bound|) (6.3h);
 *   solve (6.10) from (v = u~, z = its rollout), multipliers 0 (Q_bound);
 *   converged: v := its v                                      BAL_MO_LYAP_OK
 *   else v := u~, feasible for (6.3b-h) (Assumption 6.7.2-3)  BAL_MO_LYAP_WARM_START
 *   apply u = v_0; store x, u, v for the next step.
 *   x NaN/inf, NULL args -> u_p (NaN -> 0) clipped to U       BAL_MO_LYAP_BAD_INPUT
 *   u_p NaN/inf (x finite) -> those entries read as 0, the step runs as usual
 * Q_values(work, out): out[0] = switch (1: xi_f chosen, 0: xi_c or the first step),
 * out[1] = the bound of (6.10), out[2] = V((x, v)) of the applied plan (NAN where not
 * computed).
 */
#ifndef BAL_STEP
#error "bal/multiobj_lyap.h: define BAL_STEP (the step's symbol prefix) first"
#endif

typedef struct BAL_QX(work) {
  BAL_QX(first_work) first;
  BAL_QX(problem_work) problem;
  casadi_real p_first[BAL_QX(first_NP) + 1], p_problem[BAL_QX(problem_NP) + 1];
  casadi_real u_tilde[BAL_QX(NU) * BAL_QX(N)];        /* the warm start u~_k */
  casadi_real cand_c[BAL_QX(NU) * BAL_QX(N)], cand_f[BAL_QX(NU) * BAL_QX(N)];
  casadi_real z_tilde[BAL_QX(NX) * (BAL_QX(N) + 1)];  /* its rollout */
  casadi_real x_prev[BAL_QX(NX)], u_prev[BAL_QX(NU)], v_prev[BAL_QX(NU) * BAL_QX(N)];
  casadi_real values[3];                              /* switch, V_bound, V */
  casadi_real u_p[BAL_QX(NU)];
  const casadi_real* arg[BAL_QX(SZ_ARG)];
  casadi_real* res[BAL_QX(SZ_RES)];
  casadi_int iw[BAL_QX(SZ_IW) + 1];
  casadi_real w[BAL_QX(SZ_W) + 1];
  int have_prev, n_replaced;
  int first_status, problem_status; /* BAL_* of the last step's solves */
  int ready;
} BAL_QX(work);

/* reset: forget the previous step (the next step solves (6.3) again) */
BAL_DECLARE_STEP_LIFECYCLE(BAL_QX)
int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, casadi_real* u_out,
                 int* status, BAL_QX(work)* wk);
/* solve_status which: 0 (6.3), 1 (6.10) */
BAL_DECLARE_PAIR_ACCESSORS(BAL_QX, first, problem, init_problem, main_problem)
void BAL_QX(values)(const BAL_QX(work)* wk, casadi_real* out);
