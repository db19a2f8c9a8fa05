/* bal/rapsf_hot.h: the Algorithm 4.1 control step Q = BAL_STEP (thesis Chapter 4, SPEC
 * §2.21) with (4.5) solved by a dense dual active-set QP solver whose workspace is kept
 * across steps (hot start from the last working set), the C form of the default RAPSF
 * (preset fast-convex-sized: docs/deploy_c.md, "Session 15"). Included by the generated
 * <name>.h. The QP is the direct backend's lowered (4.5):
 *   min 1/2 y'P y + q(p)'y  s.t.  A(p)[:M0] y = b(p)[:M0],  A(p)[M0:] y <= b(p)[M0:]
 * with q = q0 + Qq p, b = b0 + Bb p, the values of A(p) = A0 + Ap p on a fixed pattern, and
 * p = (x0, u_p, theta, s) packed as the Python problem packs them (<name>_config.h).
 * Two such QPs when Q_SHARED: (4.5) with the rows of (4.5c) that coincide between vertices
 * written once (used when the vertex data make them coincide, the check of
 * balustrade.problems.rapsf.rows_shared, as the Python step decides), and (4.5) with every
 * row (any data); each keeps its own workspace.
 *
 * Q_step(x, u_p, theta, s, falsified, u_out, status, work): the arguments of bal/rapsf.h.
 * Per step, as balustrade.control.rapsf.RAPSF on its default target:
 *   solve (4.5) hot (proximal-point iterations on a singular P, bal/rapsf_hot.c); the
 *   answer is used only if the solver's flag is optimal AND the KKT residual of the lowered
 *   QP (per-row/entry scaled, as kkt_residual of the Python engine) is <= Q_KKT_TOL;
 *   otherwise the workspace is set up again and (4.5) solved cold, with the same check
 *   (Q_qp_info: retried 1);
 *   used -> u = K x + v*_0, store the plan, k_inf := 0               BAL_RAPSF_OK
 *   else k_inf := k_inf + 1; k_inf <= N - 1 with a plan -> K x + v*_{k_inf}
 *                                                                    BAL_RAPSF_STORED_PLAN
 *        else the backup K x                                         BAL_RAPSF_BACKUP
 *   falsified -> K x, nothing solved                                 BAL_RAPSF_FALSIFIED
 *   x NaN/inf or NULL arguments -> K x with NaN entries as 0          BAL_RAPSF_BAD_INPUT
 *   u_p NaN/inf entries are read as 0.
 * Where Python's engine hands an unverified answer to its sparse interior-point fallback,
 * the C retries cold and then uses the stored plan: the two differ only on such steps
 * (Q_qp_info tells them apart).
 */
#ifndef BAL_STEP
#error "bal/rapsf_hot.h: define BAL_STEP (the step's symbol prefix) first"
#endif
#include "daqp/api.h"
/* the solver's headers define these short names as macros of their own */
#undef NX
#undef N_CONSTR
#undef N_SIMPLE

#ifndef BAL_RAPSF_HOT_QP_DEFINED
#define BAL_RAPSF_HOT_QP_DEFINED
/* the constant data of one lowered QP (arrays of <name>_config.h) */
typedef struct bal_hot_data {
  int n, m, m0, nnz;
  const int *p_colptr, *p_row, *qq_ptr, *qq_col, *bb_ptr, *bb_col, *a_colptr, *a_row;
  const int *ap_ptr, *ap_col, *vidx;
  const double *p_val, *q0, *qq_val, *b0, *bb_val, *a0, *ap_val;
  const int *oc_ptr, *oc_col; /* the cost's part in p alone: 1/2 p'Cp + g'p + c0 */
  const double *oc_val, *og;
  double o0;
} bal_hot_data;

/* one lowered QP with its solver workspace, kept across steps */
typedef struct bal_hot_qp {
  const bal_hot_data* d;
  DAQPProblem qp;
  DAQPSettings settings;
  DAQPWorkspace daqp;
  DAQPResult res;
  int have_ws; /* daqp holds a set-up workspace (its working set is the hot start) */
  /* malloc'ed by init: dense H (n x n) and A (m x n, row-major), the bounds, the
     solver's f, the result, the values of A(p) now and at the last scatter, q(p), b(p),
     residual work, the proximal weights and centre, the rows' senses, the rows' units
     n_i = max_j |A_ij| of the KKT check */
  double *H, *A, *bu, *bl, *f, *x, *lam, *aval, *alast, *q, *b, *r, *Py, *ATz, *reg, *centre;
  double* nrm;
  int* sense;
  double kkt;
  int flag, iterations, retried, a_changed;
} bal_hot_qp;
#endif

typedef struct BAL_QX(work) {
  bal_hot_qp qps[2]; /* 0: every row; 1: the shared rows (Q_SHARED) */
  int used;          /* the QP of the last step */
  casadi_real p[BAL_QX(NP)];
  casadi_real plan[BAL_QX(NU) * BAL_QX(N)]; /* v* of the last verified (4.5) */
  casadi_real u_p[BAL_QX(NU)];
  casadi_real objective; /* the cost of the last verified (4.5), else NAN */
  int have_plan, k_inf, main_status, n_replaced, ready;
} BAL_QX(work);

BAL_DECLARE_STEP_LIFECYCLE(BAL_QX)
int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, const casadi_real* theta,
                 const casadi_real* s, int falsified, casadi_real* u_out, int* status,
                 BAL_QX(work)* wk);
/* BAL_OK if the last step used a verified (4.5), BAL_NOT_CONVERGED if both attempts failed
   the flag or KKT check, BAL_EVAL_ERROR if the solver's set-up failed, BAL_NOT_RUN if no
   solve ran */
int BAL_QX(solve_status)(const BAL_QX(work)* wk);
/* always BAL_NOT_RUN: no Remark 4.6 solve in this step (the interface of bal/rapsf.h) */
int BAL_QX(shrunk_status)(const BAL_QX(work)* wk);
int BAL_QX(k_inf)(const BAL_QX(work)* wk);
casadi_real BAL_QX(objective)(const BAL_QX(work)* wk);
/* out[0..5] := the solver's flag, KKT residual, iterations of the last step's solve,
   whether it retried cold (1), whether A(p) changed (1), which QP (0 every row, 1 shared) */
void BAL_QX(qp_info)(const BAL_QX(work)* wk, double* out);
/* y and the multipliers (>= 0 on the inequality rows) of the last step's QP (sizes: the
   QP of qp_info's out[5]) */
const double* BAL_QX(qp_primal)(const BAL_QX(work)* wk);
const double* BAL_QX(qp_dual)(const BAL_QX(work)* wk);
