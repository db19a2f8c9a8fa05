/* bal/rapsf_hot.c: the Algorithm 4.1 control step Q = BAL_STEP of bal/rapsf_hot.h, (4.5)
 * solved by the dense dual active-set solver of the casadi wheel (its C library, linked)
 * with its workspace kept across steps. From <name>_config.h: Q_NX, Q_NU, Q_N, Q_NQ, Q_NTH,
 * Q_NXR, Q_K (NU x NX, column-major), Q_NP and the offsets Q_P_x0, Q_P_u_p, Q_P_theta,
 * Q_P_s of the parameter vector, the lowered QP (Q_NY variables, Q_M rows of which the
 * first Q_M0 are equalities): P as CSC (Q_P_COLPTR, Q_P_ROW, Q_P_VAL, full symmetric),
 * q0 and Qq (CSR over p), b0 and Bb (CSR), the pattern of A (Q_A_COLPTR, Q_A_ROW), its
 * constant values Q_A0 and their parametric part Ap (CSR, one row per value), the indices
 * Q_VIDX of v (NU x N, column-major) in y, the solver's Q_PRIMAL_TOL, the weight Q_PROX
 * and the limit Q_PROX_ITER of the proximal iterations, and Q_KKT_TOL.
 *
 * A singular P (the cost of (4.5) weighs v_0 - u_p only) gets the semi-proximal term
 * Q_PROX/2 |y_j - c_j|^2 on its zero diagonal entries j, and the proximal-point iterations
 * run here, each a hot solve from the last working set with only q changed: the centre c
 * is the last answer (of this or the previous step), so consecutive steps start close.
 * An iterate is an answer of the original QP when its KKT residual (P, q, A(p), b(p),
 * without the proximal term) is <= Q_KKT_TOL; the iterations stop there. (The library's
 * own proximal loop restarts every solve from c = 0: more iterations, measured in
 * docs/deploy_c.md "Session 15".)
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "daqp/api.h"
#include "daqp/utils.h"
/* the solver's headers define these short names as macros of its own */
#undef NX
#undef N_CONSTR
#undef N_SIMPLE

#include "step_common.c"

static const casadi_real BAL_QX(gain)[BAL_QX(NU) * BAL_QX(NX)] = BAL_QX(K);
static const int BAL_QX(p_colptr)[BAL_QX(NY) + 1] = BAL_QX(P_COLPTR);
static const int BAL_QX(p_row)[] = BAL_QX(P_ROW);
static const double BAL_QX(p_val)[] = BAL_QX(P_VAL);
static const double BAL_QX(q0)[BAL_QX(NY)] = BAL_QX(Q0);
static const int BAL_QX(qq_ptr)[BAL_QX(NY) + 1] = BAL_QX(QQ_PTR);
static const int BAL_QX(qq_col)[] = BAL_QX(QQ_COL);
static const double BAL_QX(qq_val)[] = BAL_QX(QQ_VAL);
static const double BAL_QX(b0)[BAL_QX(M)] = BAL_QX(B0);
static const int BAL_QX(bb_ptr)[BAL_QX(M) + 1] = BAL_QX(BB_PTR);
static const int BAL_QX(bb_col)[] = BAL_QX(BB_COL);
static const double BAL_QX(bb_val)[] = BAL_QX(BB_VAL);
static const int BAL_QX(a_colptr)[BAL_QX(NY) + 1] = BAL_QX(A_COLPTR);
static const int BAL_QX(a_row)[BAL_QX(NNZ)] = BAL_QX(A_ROW);
static const double BAL_QX(a0)[BAL_QX(NNZ)] = BAL_QX(A0);
static const int BAL_QX(ap_ptr)[BAL_QX(NNZ) + 1] = BAL_QX(AP_PTR);
static const int BAL_QX(ap_col)[] = BAL_QX(AP_COL);
static const double BAL_QX(ap_val)[] = BAL_QX(AP_VAL);
static const int BAL_QX(vidx)[BAL_QX(NU) * BAL_QX(N)] = BAL_QX(VIDX);

/* out := c + S p for the CSR matrix S (rows entries) */
static void BAL_QX(affine)(const double* c, const int* ptr, const int* col, const double* val,
                           int rows, const casadi_real* p, double* out) {
  int i, k;
  for (i = 0; i < rows; ++i) {
    out[i] = c[i];
    for (k = ptr[i]; k < ptr[i + 1]; ++k) out[i] += val[k] * p[col[k]];
  }
}

/* the solver's workspace given back (nothing if none is held) */
static void BAL_QX(drop)(BAL_QX(work)* wk) {
  if (!wk->have_ws) return;
  wk->daqp.settings = 0; /* ours: not freed by the solver */
  free_daqp_workspace(&wk->daqp);
  free_daqp_ldp(&wk->daqp);
  memset(&wk->daqp, 0, sizeof(wk->daqp));
  wk->have_ws = 0;
}

int BAL_QX(init)(BAL_QX(work)* wk) {
  const int n = BAL_QX(NY), m = BAL_QX(M);
  int j, k;
  memset(wk, 0, sizeof(*wk));
  wk->H = (double*) calloc((size_t) n * n, sizeof(double));
  wk->A = (double*) calloc((size_t) m * n, sizeof(double));
  wk->bu = (double*) calloc(m, sizeof(double));
  wk->bl = (double*) calloc(m, sizeof(double));
  wk->f = (double*) calloc(n, sizeof(double));
  wk->x = (double*) calloc(n, sizeof(double));
  wk->lam = (double*) calloc(m, sizeof(double));
  wk->aval = (double*) calloc(BAL_QX(NNZ), sizeof(double));
  wk->alast = (double*) calloc(BAL_QX(NNZ), sizeof(double));
  wk->b = (double*) calloc(m, sizeof(double));
  wk->r = (double*) calloc(m, sizeof(double));
  wk->Py = (double*) calloc(n, sizeof(double));
  wk->ATz = (double*) calloc(n, sizeof(double));
  wk->sense = (int*) calloc(m, sizeof(int));
  wk->q = (double*) calloc(n, sizeof(double));
  wk->reg = (double*) calloc(n, sizeof(double));
  wk->centre = (double*) calloc(n, sizeof(double));
  if (!wk->H || !wk->A || !wk->bu || !wk->bl || !wk->f || !wk->x || !wk->lam || !wk->aval ||
      !wk->alast || !wk->b || !wk->r || !wk->Py || !wk->ATz || !wk->sense || !wk->q ||
      !wk->reg || !wk->centre) {
    wk->ready = 1;
    BAL_QX(finalize)(wk);
    return -1;
  }
  for (j = 0; j < n; ++j) {
    for (k = BAL_QX(p_colptr)[j]; k < BAL_QX(p_colptr)[j + 1]; ++k)
      wk->H[BAL_QX(p_row)[k] * n + j] = BAL_QX(p_val)[k];
  }
  for (j = 0; j < n; ++j) { /* the semi-proximal term on the zero diagonal entries */
    wk->reg[j] = wk->H[(size_t) j * n + j] == 0.0 ? BAL_QX(PROX) : 0.0;
    wk->H[(size_t) j * n + j] += wk->reg[j];
  }
  wk->qp.n = n;
  wk->qp.m = m;
  wk->qp.ms = 0;
  wk->qp.H = wk->H;
  wk->qp.f = wk->f;
  wk->qp.A = wk->A;
  wk->qp.bupper = wk->bu;
  wk->qp.blower = wk->bl;
  wk->qp.sense = wk->sense;
  daqp_default_settings(&wk->settings);
  wk->settings.primal_tol = BAL_QX(PRIMAL_TOL);
  wk->settings.eps_prox = 0; /* the proximal iterations run here (Q_PROX) */
  wk->res.x = wk->x;
  wk->res.lam = wk->lam;
  wk->ready = 1;
  BAL_QX(reset)(wk);
  return 0;
}

void BAL_QX(finalize)(BAL_QX(work)* wk) {
  if (!wk->ready) return;
  BAL_QX(drop)(wk);
  free(wk->H); free(wk->A); free(wk->bu); free(wk->bl); free(wk->f); free(wk->x);
  free(wk->lam); free(wk->aval); free(wk->alast); free(wk->b); free(wk->r); free(wk->Py);
  free(wk->ATz); free(wk->sense); free(wk->q); free(wk->reg); free(wk->centre);
  wk->H = wk->A = wk->bu = wk->bl = wk->f = wk->x = wk->lam = wk->aval = wk->alast = 0;
  wk->b = wk->r = wk->Py = wk->ATz = wk->q = wk->reg = wk->centre = 0;
  wk->sense = 0;
  wk->ready = 0;
}

BAL_DEFINE_ALLOC_FREE(BAL_QX)

void BAL_QX(reset)(BAL_QX(work)* wk) {
  (void) bal_clip;
  BAL_QX(drop)(wk); /* a new closed loop starts cold, as a new Python controller */
  memset(wk->centre, 0, BAL_QX(NY) * sizeof(double));
  wk->have_plan = 0;
  wk->k_inf = BAL_QX(N) - 1;
  wk->main_status = BAL_NOT_RUN;
  wk->n_replaced = 0;
  wk->objective = NAN;
  wk->kkt = NAN;
  wk->flag = 0;
  wk->iterations = 0;
  wk->retried = 0;
  wk->a_changed = 0;
}

/* the KKT residual of the lowered QP at (x, lam), each error scaled by its own terms
   (kkt_residual of the Python engine): stationarity entry j / (1 + max(|q_j|, |(Py)_j|,
   |(A'z)_j|)); primal feasibility and complementarity of row i / (1 + |b_i|) (an infinite
   b_i is no row); a negative multiplier of an inequality / (1 + the largest of those) */
static double BAL_QX(kkt_residual)(BAL_QX(work)* wk) {
  const int n = BAL_QX(NY), m = BAL_QX(M), m0 = BAL_QX(M0);
  const double *y = wk->x, *z = wk->lam;
  double stat = 0, prim = 0, dual = 0, comp = 0, mag, magmax = 0, e, scale;
  int i, j, k, finite;
  for (i = 0; i < m; ++i) wk->r[i] = isfinite(wk->b[i]) ? -wk->b[i] : 0.0;
  for (j = 0; j < n; ++j) {
    wk->ATz[j] = 0;
    wk->Py[j] = 0;
    for (k = BAL_QX(a_colptr)[j]; k < BAL_QX(a_colptr)[j + 1]; ++k) {
      wk->r[BAL_QX(a_row)[k]] += wk->aval[k] * y[j];
      wk->ATz[j] += wk->aval[k] * z[BAL_QX(a_row)[k]];
    }
    for (k = BAL_QX(p_colptr)[j]; k < BAL_QX(p_colptr)[j + 1]; ++k)
      wk->Py[BAL_QX(p_row)[k]] += BAL_QX(p_val)[k] * y[j];
  }
  for (j = 0; j < n; ++j) {
    mag = fmax(fmax(fabs(wk->q[j]), fabs(wk->Py[j])), fabs(wk->ATz[j]));
    if (mag > magmax) magmax = mag;
    e = fabs(wk->Py[j] + wk->q[j] + wk->ATz[j]) / (1.0 + mag);
    if (!(e <= stat)) stat = e; /* NaN propagates */
  }
  for (i = 0; i < m; ++i) {
    finite = isfinite(wk->b[i]);
    scale = 1.0 + (finite ? fabs(wk->b[i]) : 0.0);
    if (i < m0) {
      e = fabs(wk->r[i]) / scale;
      if (!(e <= prim)) prim = e;
      continue;
    }
    if (finite) {
      e = wk->r[i] / scale;
      if (!(e <= prim)) prim = e;
      e = fabs(z[i] * wk->r[i]) / scale;
      if (!(e <= comp)) comp = e;
    }
    if (!(-z[i] <= dual)) dual = -z[i];
  }
  dual /= 1.0 + magmax;
  e = fmax(fmax(stat, prim), fmax(dual, comp));
  return isfinite(e) && isfinite(stat + prim + dual + comp) ? e : NAN;
}

/* one solve with the data in wk (f, bu, bl, A): hot from the held workspace (an update of
   f, the bounds and, when they changed (a_changed, first of a step only), the values of A
   with the working set activated again), or a new set-up when none is held; returns the
   solver's flag (< 0 set-up or update failures included) */
static int BAL_QX(solve_qp)(BAL_QX(work)* wk, int first) {
  int flag, i;
  if (!wk->have_ws) {
    for (i = 0; i < BAL_QX(M); ++i) wk->sense[i] = i < BAL_QX(M0) ? ACTIVE + IMMUTABLE : 0;
    memset(&wk->daqp, 0, sizeof(wk->daqp));
    wk->daqp.settings = &wk->settings;
    flag = setup_daqp(&wk->qp, &wk->daqp, NULL);
    if (flag < 0) {
      memset(&wk->daqp, 0, sizeof(wk->daqp)); /* freed by the failed set-up */
      return flag;
    }
    wk->have_ws = 1;
  } else {
    /* a new A resets the factorization but keeps the working set's marks: activate them
       again (what the set-up does), so the solve starts from the last working set */
    int new_a = first && wk->a_changed;
    flag = update_ldp(new_a ? UPDATE_M + UPDATE_v + UPDATE_d : UPDATE_v + UPDATE_d, &wk->daqp);
    if (flag >= 0 && new_a) flag = activate_constraints(&wk->daqp);
    if (flag < 0) {
      BAL_QX(drop)(wk);
      return flag;
    }
  }
  daqp_solve(&wk->res, &wk->daqp);
  wk->iterations += wk->res.iter;
  return wk->res.exitflag;
}

/* (4.5) at the parameters wk->p: the data, a hot solve, and a cold one if the hot answer is
   not verified; returns 1 when an answer passed (flag optimal, KKT <= Q_KKT_TOL) */
static int BAL_QX(solve)(BAL_QX(work)* wk) {
  const int n = BAL_QX(NY), m = BAL_QX(M);
  int j, k, attempt, it;
  BAL_QX(affine)(BAL_QX(q0), BAL_QX(qq_ptr), BAL_QX(qq_col), BAL_QX(qq_val), n, wk->p, wk->q);
  BAL_QX(affine)(BAL_QX(b0), BAL_QX(bb_ptr), BAL_QX(bb_col), BAL_QX(bb_val), m, wk->p, wk->b);
  BAL_QX(affine)(BAL_QX(a0), BAL_QX(ap_ptr), BAL_QX(ap_col), BAL_QX(ap_val), BAL_QX(NNZ),
                 wk->p, wk->aval);
  for (j = 0; j < m; ++j) {
    wk->bu[j] = isfinite(wk->b[j]) && wk->b[j] < DAQP_INF ? wk->b[j] : DAQP_INF;
    wk->bl[j] = j < BAL_QX(M0) ? wk->bu[j] : -DAQP_INF;
  }
  wk->a_changed = memcmp(wk->aval, wk->alast, BAL_QX(NNZ) * sizeof(double)) != 0;
  if (wk->a_changed || !wk->have_ws) {
    memcpy(wk->alast, wk->aval, BAL_QX(NNZ) * sizeof(double));
    for (j = 0; j < n; ++j) {
      for (k = BAL_QX(a_colptr)[j]; k < BAL_QX(a_colptr)[j + 1]; ++k)
        wk->A[(size_t) BAL_QX(a_row)[k] * n + j] = wk->aval[k];
    }
  }
  wk->iterations = 0;
  wk->retried = 0;
  for (attempt = 0; attempt < 2; ++attempt) {
    if (attempt) { /* the hot answer failed: set up again, cold */
      BAL_QX(drop)(wk);
      wk->retried = 1;
    }
    if (attempt) memset(wk->centre, 0, n * sizeof(double));
    for (it = 0; it < BAL_QX(PROX_ITER); ++it) { /* proximal-point iterations, each hot */
      for (j = 0; j < n; ++j) wk->f[j] = wk->q[j] - wk->reg[j] * wk->centre[j];
      wk->flag = BAL_QX(solve_qp)(wk, it == 0);
      wk->kkt = NAN;
      if (wk->flag != EXIT_OPTIMAL) break;
      memcpy(wk->centre, wk->x, n * sizeof(double));
      wk->kkt = BAL_QX(kkt_residual)(wk);
      if (wk->kkt <= BAL_QX(KKT_TOL)) return 1;
      if (!(wk->kkt == wk->kkt)) break; /* NaN: no answer */
    }
  }
  BAL_QX(drop)(wk); /* the next step sets up anew */
  return 0;
}

/* u := K x + v (v may be 0: the backup K x); NaN entries of x count as 0 */
static void BAL_QX(feedback)(const casadi_real* x, const casadi_real* v, casadi_real* u) {
  int i, j;
  for (i = 0; i < BAL_QX(NU); ++i) {
    u[i] = v ? v[i] : 0.0;
    for (j = 0; j < BAL_QX(NX); ++j)
      u[i] += BAL_QX(gain)[i + j * BAL_QX(NU)] * (isfinite(x[j]) ? x[j] : 0.0);
  }
}

int BAL_QX(step)(const casadi_real* x, const casadi_real* u_p, const casadi_real* theta,
                 const casadi_real* s, int falsified, casadi_real* u_out, int* status,
                 BAL_QX(work)* wk) {
  int i;
  double obj;
  if (!x || !u_p || !theta || !s || !u_out || !status || !wk || !wk->ready) {
    if (status) *status = BAL_RAPSF_BAD_INPUT;
    if (x && u_out) BAL_QX(feedback)(x, 0, u_out);
    return BAL_RAPSF_BAD_INPUT;
  }
  wk->main_status = BAL_NOT_RUN;
  wk->objective = NAN;
  wk->n_replaced = bal_read_proposal(u_p, wk->u_p, BAL_QX(NU));
  if (falsified || !bal_finite(x, BAL_QX(NX))) {
    BAL_QX(feedback)(x, 0, u_out); /* nothing solved; k_inf and the plan are kept */
    *status = falsified ? BAL_RAPSF_FALSIFIED : BAL_RAPSF_BAD_INPUT;
    return *status;
  }
  for (i = 0; i < BAL_QX(NX); ++i) wk->p[BAL_QX(P_x0) + i] = x[i];
  for (i = 0; i < BAL_QX(NU); ++i) wk->p[BAL_QX(P_u_p) + i] = wk->u_p[i];
  memcpy(wk->p + BAL_QX(P_theta), theta, BAL_QX(NQ) * BAL_QX(NTH) * sizeof(casadi_real));
  memcpy(wk->p + BAL_QX(P_s), s, BAL_QX(NXR) * BAL_QX(NTH) * sizeof(casadi_real));
  if (BAL_QX(solve)(wk)) {
    wk->main_status = BAL_OK;
    for (i = 0; i < BAL_QX(NU) * BAL_QX(N); ++i) wk->plan[i] = wk->x[BAL_QX(vidx)[i]];
    obj = 0;
    for (i = 0; i < BAL_QX(NY); ++i) obj += (0.5 * wk->Py[i] + wk->q[i]) * wk->x[i];
    wk->objective = obj;
    wk->have_plan = 1;
    wk->k_inf = 0;
    BAL_QX(feedback)(x, wk->plan, u_out);
    *status = BAL_RAPSF_OK;
    return *status;
  }
  wk->main_status = wk->flag < 0 && wk->flag != EXIT_INFEASIBLE && wk->flag != EXIT_CYCLE &&
                            wk->flag != EXIT_ITERLIMIT ? BAL_EVAL_ERROR : BAL_NOT_CONVERGED;
  wk->k_inf += 1;
  if (wk->k_inf <= BAL_QX(N) - 1 && wk->have_plan) {
    BAL_QX(feedback)(x, wk->plan + wk->k_inf * BAL_QX(NU), u_out);
    *status = BAL_RAPSF_STORED_PLAN;
  } else {
    BAL_QX(feedback)(x, 0, u_out);
    *status = BAL_RAPSF_BACKUP;
  }
  return *status;
}

int BAL_QX(solve_status)(const BAL_QX(work)* wk) { return wk->main_status; }
int BAL_QX(shrunk_status)(const BAL_QX(work)* wk) { (void) wk; return BAL_NOT_RUN; }
int BAL_QX(k_inf)(const BAL_QX(work)* wk) { return wk->k_inf; }
casadi_real BAL_QX(objective)(const BAL_QX(work)* wk) { return wk->objective; }
int BAL_QX(proposal_replaced)(const BAL_QX(work)* wk) { return wk->n_replaced; }
void BAL_QX(qp_info)(const BAL_QX(work)* wk, double* out) {
  out[0] = wk->flag;
  out[1] = wk->kkt;
  out[2] = wk->iterations;
  out[3] = wk->retried;
  out[4] = wk->a_changed;
}
const double* BAL_QX(qp_primal)(const BAL_QX(work)* wk) { return wk->x; }
const double* BAL_QX(qp_dual)(const BAL_QX(work)* wk) { return wk->lam; }
