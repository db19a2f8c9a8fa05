/* bal/rapsf_hot.c: the Algorithm 4.1 control step Q = BAL_STEP of bal/rapsf_hot.h, (4.5)
 * solved by the dense dual active-set solver of the casadi wheel (its C library, linked)
 * with its workspace kept across steps. From <name>_config.h: Q_NX, Q_NU, Q_N, Q_NQ, Q_NTH,
 * Q_NXR, Q_K (NU x NX, column-major), Q_NP and the offsets Q_P_x0, Q_P_u_p, Q_P_theta,
 * Q_P_s of the parameter vector; per lowered QP T (ALL: every row; SH: the shared rows,
 * when Q_SHARED) its sizes Q_T_NY, Q_T_M, Q_T_M0 (equality rows, the first), Q_T_NNZ, P as
 * CSC (Q_T_P_COLPTR, _P_ROW, _P_VAL, full symmetric), q0 and Qq (CSR over p: Q_T_Q0,
 * Q_T_QQ_PTR/_COL/_VAL), b0 and Bb (Q_T_B0, Q_T_BB_*), the pattern of A (Q_T_A_COLPTR,
 * Q_T_A_ROW), its constant values Q_T_A0 and their parametric part (Q_T_AP_*, one row per
 * value), the cost's part in p alone (Q_T_OC_* CSR, Q_T_OG, Q_T_O0: 1/2 p'Cp + g'p + c0,
 * added to the reported objective), the indices Q_T_VIDX of v (NU x N, column-major) in y;
 * with Q_SHARED the map
 * Q_REP (NXR x NTH) of the merged rows and Q_DEP (NXR x NQ: row r depends on theta_k);
 * the solver's Q_PRIMAL_TOL, the weight Q_PROX and limit Q_PROX_ITER of the proximal
 * iterations, and Q_KKT_TOL.
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
#undef NX /* as in bal/rapsf_hot.h */
#undef N_CONSTR
#undef N_SIMPLE

#include "step_common.c"

static const casadi_real BAL_QX(gain)[BAL_QX(NU) * BAL_QX(NX)] = BAL_QX(K);

/* the constant arrays of the lowered QP T and their bal_hot_data */
#define BAL_HOT_DATA(T)                                                                  \
  static const int BAL_QX(T##_p_colptr)[] = BAL_QX(T##_P_COLPTR);                        \
  static const int BAL_QX(T##_p_row)[] = BAL_QX(T##_P_ROW);                              \
  static const double BAL_QX(T##_p_val)[] = BAL_QX(T##_P_VAL);                           \
  static const double BAL_QX(T##_q0)[] = BAL_QX(T##_Q0);                                 \
  static const int BAL_QX(T##_qq_ptr)[] = BAL_QX(T##_QQ_PTR);                            \
  static const int BAL_QX(T##_qq_col)[] = BAL_QX(T##_QQ_COL);                            \
  static const double BAL_QX(T##_qq_val)[] = BAL_QX(T##_QQ_VAL);                         \
  static const double BAL_QX(T##_b0)[] = BAL_QX(T##_B0);                                 \
  static const int BAL_QX(T##_bb_ptr)[] = BAL_QX(T##_BB_PTR);                            \
  static const int BAL_QX(T##_bb_col)[] = BAL_QX(T##_BB_COL);                            \
  static const double BAL_QX(T##_bb_val)[] = BAL_QX(T##_BB_VAL);                         \
  static const int BAL_QX(T##_a_colptr)[] = BAL_QX(T##_A_COLPTR);                        \
  static const int BAL_QX(T##_a_row)[] = BAL_QX(T##_A_ROW);                              \
  static const double BAL_QX(T##_a0)[] = BAL_QX(T##_A0);                                 \
  static const int BAL_QX(T##_ap_ptr)[] = BAL_QX(T##_AP_PTR);                            \
  static const int BAL_QX(T##_ap_col)[] = BAL_QX(T##_AP_COL);                            \
  static const double BAL_QX(T##_ap_val)[] = BAL_QX(T##_AP_VAL);                         \
  static const int BAL_QX(T##_oc_ptr)[] = BAL_QX(T##_OC_PTR);                            \
  static const int BAL_QX(T##_oc_col)[] = BAL_QX(T##_OC_COL);                            \
  static const double BAL_QX(T##_oc_val)[] = BAL_QX(T##_OC_VAL);                         \
  static const double BAL_QX(T##_og)[] = BAL_QX(T##_OG);                                 \
  static const int BAL_QX(T##_vidx)[BAL_QX(NU) * BAL_QX(N)] = BAL_QX(T##_VIDX);          \
  static const bal_hot_data BAL_QX(T##_data) = {                                         \
      BAL_QX(T##_NY), BAL_QX(T##_M), BAL_QX(T##_M0), BAL_QX(T##_NNZ),                    \
      BAL_QX(T##_p_colptr), BAL_QX(T##_p_row), BAL_QX(T##_qq_ptr), BAL_QX(T##_qq_col),   \
      BAL_QX(T##_bb_ptr), BAL_QX(T##_bb_col), BAL_QX(T##_a_colptr), BAL_QX(T##_a_row),   \
      BAL_QX(T##_ap_ptr), BAL_QX(T##_ap_col), BAL_QX(T##_vidx), BAL_QX(T##_p_val),       \
      BAL_QX(T##_q0), BAL_QX(T##_qq_val), BAL_QX(T##_b0), BAL_QX(T##_bb_val),            \
      BAL_QX(T##_a0), BAL_QX(T##_ap_val), BAL_QX(T##_oc_ptr), BAL_QX(T##_oc_col),        \
      BAL_QX(T##_oc_val), BAL_QX(T##_og), BAL_QX(T##_O0)};
BAL_HOT_DATA(ALL)
#if BAL_QX(SHARED)
BAL_HOT_DATA(SH)
static const int BAL_QX(rep)[BAL_QX(NXR) * BAL_QX(NTH)] = BAL_QX(REP);
static const int BAL_QX(dep)[BAL_QX(NXR) * BAL_QX(NQ)] = BAL_QX(DEP);
#endif
#undef BAL_HOT_DATA

#ifndef BAL_RAPSF_HOT_FUNCTIONS
#define BAL_RAPSF_HOT_FUNCTIONS
/* out := c + S p for the CSR matrix S (rows entries) */
static void bal_hot_affine(const double* c, const int* ptr, const int* col, const double* val,
                           int rows, const casadi_real* p, double* out) {
  int i, k;
  for (i = 0; i < rows; ++i) {
    out[i] = c[i];
    for (k = ptr[i]; k < ptr[i + 1]; ++k) out[i] += val[k] * p[col[k]];
  }
}

/* the solver's workspace given back (nothing if none is held) */
static void bal_hot_drop(bal_hot_qp* h) {
  if (!h->have_ws) return;
  h->daqp.settings = 0; /* ours: not freed by the solver */
  free_daqp_workspace(&h->daqp);
  free_daqp_ldp(&h->daqp);
  memset(&h->daqp, 0, sizeof(h->daqp));
  h->have_ws = 0;
}

static void bal_hot_finalize(bal_hot_qp* h) {
  bal_hot_drop(h);
  free(h->H); free(h->A); free(h->bu); free(h->bl); free(h->f); free(h->x); free(h->lam);
  free(h->aval); free(h->alast); free(h->q); free(h->b); free(h->r); free(h->Py);
  free(h->ATz); free(h->reg); free(h->centre); free(h->sense); free(h->nrm);
  memset(h, 0, sizeof(*h));
}

/* the QP's arrays, dense H with the proximal weight on P's zero diagonal entries, the
   solver's settings; returns 0, or -1 when an allocation failed (everything given back) */
static int bal_hot_init(bal_hot_qp* h, const bal_hot_data* d, double prox, double primal_tol) {
  const int n = d->n, m = d->m;
  int j, k;
  memset(h, 0, sizeof(*h));
  h->d = d;
  h->H = (double*) calloc((size_t) n * n, sizeof(double));
  h->A = (double*) calloc((size_t) m * n, sizeof(double));
  h->bu = (double*) calloc(m, sizeof(double));
  h->bl = (double*) calloc(m, sizeof(double));
  h->f = (double*) calloc(n, sizeof(double));
  h->x = (double*) calloc(n, sizeof(double));
  h->lam = (double*) calloc(m, sizeof(double));
  h->aval = (double*) calloc(d->nnz ? d->nnz : 1, sizeof(double));
  h->alast = (double*) calloc(d->nnz ? d->nnz : 1, sizeof(double));
  h->q = (double*) calloc(n, sizeof(double));
  h->b = (double*) calloc(m, sizeof(double));
  h->r = (double*) calloc(m, sizeof(double));
  h->Py = (double*) calloc(n, sizeof(double));
  h->ATz = (double*) calloc(n, sizeof(double));
  h->reg = (double*) calloc(n, sizeof(double));
  h->centre = (double*) calloc(n, sizeof(double));
  h->sense = (int*) calloc(m, sizeof(int));
  h->nrm = (double*) calloc(m ? m : 1, sizeof(double));
  if (!h->H || !h->A || !h->bu || !h->bl || !h->f || !h->x || !h->lam || !h->aval ||
      !h->alast || !h->q || !h->b || !h->r || !h->Py || !h->ATz || !h->reg || !h->centre ||
      !h->sense || !h->nrm) {
    bal_hot_finalize(h);
    return -1;
  }
  for (j = 0; j < n; ++j) {
    for (k = d->p_colptr[j]; k < d->p_colptr[j + 1]; ++k)
      h->H[(size_t) d->p_row[k] * n + j] = d->p_val[k];
  }
  for (j = 0; j < n; ++j) { /* the semi-proximal term on the zero diagonal entries */
    h->reg[j] = h->H[(size_t) j * n + j] == 0.0 ? prox : 0.0;
    h->H[(size_t) j * n + j] += h->reg[j];
  }
  h->qp.n = n;
  h->qp.m = m;
  h->qp.ms = 0;
  h->qp.H = h->H;
  h->qp.f = h->f;
  h->qp.A = h->A;
  h->qp.bupper = h->bu;
  h->qp.blower = h->bl;
  h->qp.sense = h->sense;
  daqp_default_settings(&h->settings);
  h->settings.primal_tol = primal_tol;
  h->settings.eps_prox = 0; /* the proximal iterations run here */
  h->res.x = h->x;
  h->res.lam = h->lam;
  h->kkt = NAN;
  return 0;
}

/* a new closed loop: cold, centre 0 */
static void bal_hot_reset(bal_hot_qp* h) {
  bal_hot_drop(h);
  memset(h->centre, 0, h->d->n * sizeof(double));
  h->kkt = NAN;
  h->flag = h->iterations = h->retried = h->a_changed = 0;
}

/* the KKT residual of the lowered QP at (x, lam) (kkt_residual of the Python engine, the
   same formula): row i measured in its own unit n_i = max_j |A_ij| (1 for a zero row: the
   row and b_i divided by n_i, z_i multiplied by it), then each error scaled by its own
   terms: stationarity entry j / (1 + max(|q_j|, |(Py)_j|, |(A'z)_j|)); primal feasibility
   and complementarity of row i / (1 + |b_i| / n_i) (a b_i = +inf inequality is no row:
   neither counts); a negative n_i z_i of an inequality, or a nonzero one of a row
   b_i = +inf, / (1 + the largest of those magnitudes). NaN when any b_i is NaN or -inf or
   an equality's b_i is infinite (no point satisfies that row), or any term is not finite */
static double bal_hot_kkt(bal_hot_qp* h) {
  const bal_hot_data* d = h->d;
  const double *y = h->x, *z = h->lam;
  double stat = 0, prim = 0, dual = 0, comp = 0, mag, magmax = 0, e, scale, ri, zn;
  int i, j, k, finite;
  for (i = 0; i < d->m; ++i) {
    if (h->b[i] != h->b[i] || h->b[i] == -INFINITY || (i < d->m0 && !isfinite(h->b[i])))
      return NAN;
    h->r[i] = isfinite(h->b[i]) ? -h->b[i] : 0.0;
    h->nrm[i] = 0.0;
  }
  for (k = 0; k < d->nnz; ++k) { /* the rows' units, from the current values of A */
    e = fabs(h->aval[k]);
    if (!(e <= h->nrm[d->a_row[k]])) h->nrm[d->a_row[k]] = e;
  }
  for (i = 0; i < d->m; ++i)
    if (!(h->nrm[i] > 0.0)) h->nrm[i] = h->nrm[i] == h->nrm[i] ? 1.0 : NAN;
  for (j = 0; j < d->n; ++j) {
    h->ATz[j] = 0;
    h->Py[j] = 0;
  }
  for (j = 0; j < d->n; ++j) {
    for (k = d->a_colptr[j]; k < d->a_colptr[j + 1]; ++k) {
      h->r[d->a_row[k]] += h->aval[k] * y[j];
      h->ATz[j] += h->aval[k] * z[d->a_row[k]];
    }
    for (k = d->p_colptr[j]; k < d->p_colptr[j + 1]; ++k)
      h->Py[d->p_row[k]] += d->p_val[k] * y[j];
  }
  for (j = 0; j < d->n; ++j) {
    mag = fmax(fmax(fabs(h->q[j]), fabs(h->Py[j])), fabs(h->ATz[j]));
    if (!(mag <= magmax)) magmax = mag;
    e = fabs(h->Py[j] + h->q[j] + h->ATz[j]) / (1.0 + mag);
    if (!(e <= stat)) stat = e; /* NaN propagates */
  }
  for (i = 0; i < d->m; ++i) {
    finite = isfinite(h->b[i]);
    scale = 1.0 + (finite ? fabs(h->b[i]) / h->nrm[i] : 0.0);
    ri = h->r[i] / h->nrm[i];
    zn = z[i] * h->nrm[i];
    if (i < d->m0) {
      e = fabs(ri) / scale;
      if (!(e <= prim)) prim = e;
      continue;
    }
    if (finite) {
      e = ri / scale;
      if (!(e <= prim)) prim = e;
      e = fabs(zn * ri) / scale;
      if (!(e <= comp)) comp = e;
      e = -zn;
    } else {
      e = fabs(zn); /* a multiplier on no row is an error */
    }
    if (!(e <= dual)) dual = e;
  }
  dual /= 1.0 + magmax;
  e = fmax(fmax(stat, prim), fmax(dual, comp));
  return isfinite(e) && isfinite(stat + prim + dual + comp) ? e : NAN;
}

/* one solve with the data in h (f, bu, bl, A): hot from the held workspace (an update of
   f, the bounds and, when they changed (a_changed, first of a step only), the values of A
   with the working set activated again), or a new set-up when none is held; returns the
   solver's flag (< 0 set-up or update failures included) */
static int bal_hot_solve_once(bal_hot_qp* h, int first) {
  int flag, i, new_a;
  if (!h->have_ws) {
    for (i = 0; i < h->d->m; ++i) h->sense[i] = i < h->d->m0 ? ACTIVE + IMMUTABLE : 0;
    memset(&h->daqp, 0, sizeof(h->daqp));
    h->daqp.settings = &h->settings;
    flag = setup_daqp(&h->qp, &h->daqp, NULL);
    if (flag < 0) {
      memset(&h->daqp, 0, sizeof(h->daqp)); /* freed by the failed set-up */
      return flag;
    }
    h->have_ws = 1;
  } else {
    /* a new A resets the factorization but keeps the working set's marks: activate them
       again (what the set-up does), so the solve starts from the last working set */
    new_a = first && h->a_changed;
    flag = update_ldp(new_a ? UPDATE_M + UPDATE_v + UPDATE_d : UPDATE_v + UPDATE_d, &h->daqp);
    if (flag >= 0 && new_a) flag = activate_constraints(&h->daqp);
    if (flag < 0) {
      bal_hot_drop(h);
      return flag;
    }
  }
  daqp_solve(&h->res, &h->daqp);
  h->iterations += h->res.iter;
  return h->res.exitflag;
}

/* the QP at the parameters p: its data, the proximal iterations hot, and again cold if no
   iterate is verified; returns 1 when an answer passed (flag optimal, KKT <= kkt_tol) */
static int bal_hot_solve(bal_hot_qp* h, const casadi_real* p, int prox_iter, double kkt_tol) {
  const bal_hot_data* d = h->d;
  const int n = d->n, m = d->m;
  int j, k, attempt, it;
  bal_hot_affine(d->q0, d->qq_ptr, d->qq_col, d->qq_val, n, p, h->q);
  bal_hot_affine(d->b0, d->bb_ptr, d->bb_col, d->bb_val, m, p, h->b);
  bal_hot_affine(d->a0, d->ap_ptr, d->ap_col, d->ap_val, d->nnz, p, h->aval);
  h->iterations = 0;
  h->retried = 0;
  for (j = 0; j < m; ++j) {
    if (h->b[j] != h->b[j] || h->b[j] == -INFINITY) { /* no point satisfies row j */
      h->flag = 0;
      h->kkt = NAN;
      return 0;
    }
  }
  for (j = 0; j < m; ++j) {
    h->bu[j] = isfinite(h->b[j]) && h->b[j] < DAQP_INF ? h->b[j] : DAQP_INF;
    h->bl[j] = j < d->m0 ? h->bu[j] : -DAQP_INF;
  }
  h->a_changed = memcmp(h->aval, h->alast, d->nnz * sizeof(double)) != 0;
  if (h->a_changed || !h->have_ws) {
    memcpy(h->alast, h->aval, d->nnz * sizeof(double));
    for (j = 0; j < n; ++j) {
      for (k = d->a_colptr[j]; k < d->a_colptr[j + 1]; ++k)
        h->A[(size_t) d->a_row[k] * n + j] = h->aval[k];
    }
  }
  for (attempt = 0; attempt < 2; ++attempt) {
    if (attempt) { /* the hot answer failed: set up again, cold */
      bal_hot_drop(h);
      h->retried = 1;
      memset(h->centre, 0, n * sizeof(double));
    }
    for (it = 0; it < prox_iter; ++it) { /* proximal-point iterations, each hot */
      for (j = 0; j < n; ++j) h->f[j] = h->q[j] - h->reg[j] * h->centre[j];
      h->flag = bal_hot_solve_once(h, it == 0);
      h->kkt = NAN;
      if (h->flag != EXIT_OPTIMAL) break;
      memcpy(h->centre, h->x, n * sizeof(double));
      h->kkt = bal_hot_kkt(h);
      if (h->kkt <= kkt_tol) return 1;
      if (!(h->kkt == h->kkt)) break; /* NaN: no answer */
    }
  }
  bal_hot_drop(h); /* the next step sets up anew */
  return 0;
}
#endif /* BAL_RAPSF_HOT_FUNCTIONS */

int BAL_QX(init)(BAL_QX(work)* wk) {
  memset(wk, 0, sizeof(*wk));
  if (bal_hot_init(&wk->qps[0], &BAL_QX(ALL_data), BAL_QX(PROX), BAL_QX(PRIMAL_TOL)))
    return -1;
#if BAL_QX(SHARED)
  if (bal_hot_init(&wk->qps[1], &BAL_QX(SH_data), BAL_QX(PROX), BAL_QX(PRIMAL_TOL))) {
    bal_hot_finalize(&wk->qps[0]);
    return -1;
  }
#endif
  wk->ready = 1;
  BAL_QX(reset)(wk);
  return 0;
}

void BAL_QX(finalize)(BAL_QX(work)* wk) {
  if (!wk->ready) return;
  bal_hot_finalize(&wk->qps[0]);
#if BAL_QX(SHARED)
  bal_hot_finalize(&wk->qps[1]);
#endif
  wk->ready = 0;
}

BAL_DEFINE_ALLOC_FREE(BAL_QX)

void BAL_QX(reset)(BAL_QX(work)* wk) {
  (void) bal_clip;
  bal_hot_reset(&wk->qps[0]); /* a new closed loop starts cold, as a new Python controller */
#if BAL_QX(SHARED)
  bal_hot_reset(&wk->qps[1]);
#endif
  wk->used = 0;
  wk->have_plan = 0;
  wk->k_inf = BAL_QX(N) - 1;
  wk->main_status = BAL_NOT_RUN;
  wk->n_replaced = 0;
  wk->objective = NAN;
}

/* 1 when the vertex data repeat every merged row exactly (rows_shared of
   balustrade.problems.rapsf): s[r, j] == s[r, rep[r, j]] and theta[k, j] ==
   theta[k, rep[r, j]] for every theta_k row r depends on; the shared QP is then (4.5) */
static int BAL_QX(rows_shared)(const casadi_real* theta, const casadi_real* s) {
#if BAL_QX(SHARED)
  int r, j, k, rj;
  for (r = 0; r < BAL_QX(NXR); ++r) {
    for (j = 0; j < BAL_QX(NTH); ++j) {
      rj = BAL_QX(rep)[r + j * BAL_QX(NXR)];
      if (!(s[r + j * BAL_QX(NXR)] == s[r + rj * BAL_QX(NXR)])) return 0;
      for (k = 0; k < BAL_QX(NQ); ++k) {
        if (BAL_QX(dep)[r + k * BAL_QX(NXR)] &&
            !(theta[k + j * BAL_QX(NQ)] == theta[k + rj * BAL_QX(NQ)]))
          return 0;
      }
    }
  }
  return 1;
#else
  (void) theta;
  (void) s;
  return 0;
#endif
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
  bal_hot_qp* h;
  if (!x || !u_p || !theta || !s || !u_out || !status || !wk || !wk->ready) {
    if (status) *status = BAL_RAPSF_BAD_INPUT;
    if (x && u_out) BAL_QX(feedback)(x, 0, u_out);
    return BAL_RAPSF_BAD_INPUT;
  }
  wk->main_status = BAL_NOT_RUN;
  wk->objective = NAN;
  wk->n_replaced = bal_read_proposal(u_p, wk->u_p, BAL_QX(NU));
  if (falsified || !bal_finite(x, BAL_QX(NX)) || !bal_finite(theta, BAL_QX(NQ) * BAL_QX(NTH)) ||
      !bal_finite(s, BAL_QX(NXR) * BAL_QX(NTH))) {
    /* nothing solved (a NaN or inf theta or s is bad input, as a NaN x); k_inf and the
       plan are kept */
    BAL_QX(feedback)(x, 0, u_out);
    *status = falsified ? BAL_RAPSF_FALSIFIED : BAL_RAPSF_BAD_INPUT;
    return *status;
  }
  for (i = 0; i < BAL_QX(NX); ++i) wk->p[BAL_QX(P_x0) + i] = x[i];
  for (i = 0; i < BAL_QX(NU); ++i) wk->p[BAL_QX(P_u_p) + i] = wk->u_p[i];
  memcpy(wk->p + BAL_QX(P_theta), theta, BAL_QX(NQ) * BAL_QX(NTH) * sizeof(casadi_real));
  memcpy(wk->p + BAL_QX(P_s), s, BAL_QX(NXR) * BAL_QX(NTH) * sizeof(casadi_real));
  wk->used = BAL_QX(rows_shared)(theta, s);
  h = &wk->qps[wk->used];
  if (bal_hot_solve(h, wk->p, BAL_QX(PROX_ITER), BAL_QX(KKT_TOL))) {
    wk->main_status = BAL_OK;
    for (i = 0; i < BAL_QX(NU) * BAL_QX(N); ++i) wk->plan[i] = h->x[h->d->vidx[i]];
    obj = 0;
    for (i = 0; i < h->d->n; ++i) obj += (0.5 * h->Py[i] + h->q[i]) * h->x[i];
    obj += h->d->o0; /* the cost's part in p alone: 1/2 p'Cp + g'p + c0 */
    for (i = 0; i < BAL_QX(NP); ++i) {
      int k;
      double cp = 0.0;
      for (k = h->d->oc_ptr[i]; k < h->d->oc_ptr[i + 1]; ++k)
        cp += h->d->oc_val[k] * wk->p[h->d->oc_col[k]];
      obj += (0.5 * cp + h->d->og[i]) * wk->p[i];
    }
    wk->objective = obj;
    wk->have_plan = 1;
    wk->k_inf = 0;
    BAL_QX(feedback)(x, wk->plan, u_out);
    *status = BAL_RAPSF_OK;
    return *status;
  }
  wk->main_status = h->flag < 0 && h->flag != EXIT_INFEASIBLE && h->flag != EXIT_CYCLE &&
                            h->flag != EXIT_ITERLIMIT ? BAL_EVAL_ERROR : BAL_NOT_CONVERGED;
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
  const bal_hot_qp* h = &wk->qps[wk->used];
  out[0] = h->flag;
  out[1] = h->kkt;
  out[2] = h->iterations;
  out[3] = h->retried;
  out[4] = h->a_changed;
  out[5] = wk->used;
}
const double* BAL_QX(qp_primal)(const BAL_QX(work)* wk) { return wk->qps[wk->used].x; }
const double* BAL_QX(qp_dual)(const BAL_QX(work)* wk) { return wk->qps[wk->used].lam; }
