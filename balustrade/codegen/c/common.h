/* bal/common.h: macros shared by balustrade's static C (shipped with the package, copied
 * next to every emitted module). The generated <name>_config.h holds the numbers (sizes,
 * offsets, bounds, tolerances, status codes); the files of bal/ hold the algorithms and are
 * instantiated once per symbol prefix by the generated <name>.c:
 *
 *   #define BAL_PROBLEM pendulum_pcbf_slack   (one problem: bal/problem.h, bal/problem.c)
 *   #define BAL_STEP pendulum_pcbf            (one control step: bal/pcbf.*, approx.*, ...)
 *
 * BAL_PX(solve) is then pendulum_pcbf_slack_solve and BAL_QX(step) pendulum_pcbf_step: the
 * entry points have the real names of the emitted module.
 */
#ifndef BAL_COMMON_H
#define BAL_COMMON_H

#define BAL_CAT_(a, b) a##_##b
#define BAL_CAT(a, b) BAL_CAT_(a, b)
/* a symbol of the problem BAL_PROBLEM / of the step BAL_STEP */
#define BAL_PX(x) BAL_CAT(BAL_PROBLEM, x)
#define BAL_QX(x) BAL_CAT(BAL_STEP, x)

#define BAL_MAX2(a, b) ((a) > (b) ? (a) : (b))

/* converged and, after all retries, primal-feasible solutions are usable (a feasible point
   of (2.23)/(7.5) keeps the guarantees of the constraints; a feasible (2.24) of positive
   cost only bounds h_PB, so the PCBF step treats it as a failed (2.24)), exactly as
   balustrade.control does with the backend's "feasible" status */
#define BAL_SOLVED(s) ((s) == BAL_OK || (s) == BAL_FEASIBLE)

/* The entry points every control step X = BAL_QX declares (bal/pcbf.h, bal/approx.h,
   bal/grid.h, bal/robust.h, bal/multiobj.h): X(init) / X(finalize) of a caller-owned work
   struct (init returns 0 on success), X(alloc) / X(free) of a heap one
   (BAL_DEFINE_ALLOC_FREE), X(reset) for a new closed loop (what it forgets: the step's
   header), and X(proposal_replaced), the entries of the last step's u_p that were NaN or
   inf (replaced by 0). */
#define BAL_DECLARE_STEP_LIFECYCLE(X)                              \
  int X(init)(X(work)* wk);                                        \
  void X(finalize)(X(work)* wk);                                   \
  X(work)* X(alloc)(void);                                         \
  void X(free)(X(work)* wk);                                       \
  void X(reset)(X(work)* wk);                                      \
  int X(proposal_replaced)(const X(work)* wk);

/* The accessors of a control step X that owns two emitted problems, the members A and B
   of its work struct with their last statuses A##_status and B##_status: X(GET_A) and
   X(GET_B) return &wk->A and &wk->B (for foreign-function callers), X(solve_status)(wk,
   which) the BAL_* status of A's (which = 0) or B's last solve. */
#define BAL_DECLARE_PAIR_ACCESSORS(X, A, B, GET_A, GET_B)          \
  X(A##_work)* X(GET_A)(X(work)* wk);                              \
  X(B##_work)* X(GET_B)(X(work)* wk);                              \
  int X(solve_status)(const X(work)* wk, int which);
#define BAL_DEFINE_PAIR_ACCESSORS(X, A, B, GET_A, GET_B)           \
  X(A##_work)* X(GET_A)(X(work)* wk) { return &wk->A; }            \
  X(B##_work)* X(GET_B)(X(work)* wk) { return &wk->B; }            \
  int X(solve_status)(const X(work)* wk, int which) {              \
    return which == 0 ? wk->A##_status : wk->B##_status;           \
  }

/* The work-struct members of the candidate (5.17)/(6.14) of the tube-based steps
   (bal/robust.h, bal/multiobj.h; used by bal/tube_common.c): z~ (NX x (N+1)), v~ (NU x N),
   xi~, xi~_N, h~, and the same for the next candidate while X(cand) builds it (nok: its
   terminal input was computed exactly). */
#define BAL_TUBE_CANDIDATE_MEMBERS(X)                              \
  casadi_real cz[X(NX) * (X(N) + 1)], cv[X(NU) * X(N)];            \
  casadi_real cxi[X(N_XI)], cxi_N, ch;                             \
  casadi_real nz[X(NX) * (X(N) + 1)], nv[X(NU) * X(N)];            \
  casadi_real nxi[X(N_XI)], nxi_N, nh, nok;

/* X(alloc) and X(free) of a work struct that has X(init) and X(finalize), for X = BAL_PX or
   BAL_QX: alloc returns 0 when calloc or init fails; free accepts 0. */
#define BAL_DEFINE_ALLOC_FREE(X)                                   \
  X(work)* X(alloc)(void) {                                        \
    X(work)* wk = (X(work)*) calloc(1, sizeof(X(work)));           \
    if (wk && X(init)(wk)) {                                       \
      free(wk);                                                    \
      return 0;                                                    \
    }                                                              \
    return wk;                                                     \
  }                                                                \
  void X(free)(X(work)* wk) {                                      \
    if (!wk) return;                                               \
    X(finalize)(wk);                                               \
    free(wk);                                                      \
  }

/* X(init) and X(finalize) of a control step that owns two emitted problems, the members A
   and B of its work struct (e.g. slack and filter): init sets up A, then B (releasing A if B
   fails), cold-starts both through X(reset) and marks the work ready; finalize releases B,
   then A. */
#define BAL_DEFINE_PAIR_INIT_FINALIZE(X, A, B)                     \
  int X(init)(X(work)* wk) {                                       \
    wk->ready = 0;                                                 \
    if (X(A##_init)(&wk->A)) return -1;                            \
    if (X(B##_init)(&wk->B)) {                                     \
      X(A##_finalize)(&wk->A);                                     \
      return -1;                                                   \
    }                                                              \
    X(reset)(wk);                                                  \
    wk->ready = 1;                                                 \
    return 0;                                                      \
  }                                                                \
  void X(finalize)(X(work)* wk) {                                  \
    if (!wk->ready) return;                                        \
    X(B##_finalize)(&wk->B);                                       \
    X(A##_finalize)(&wk->A);                                       \
    wk->ready = 0;                                                 \
  }

/* One CasADi-generated function with its memory management, as written by CasADi's code
   generator: f(arg, res, iw, w, mem), f_incref, f_checkout, f_release, f_decref. */
typedef struct bal_casadi_fn {
  int (*eval)(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w,
              int mem);
  void (*incref)(void);
  int (*checkout)(void);
  void (*release)(int mem);
  void (*decref)(void);
} bal_casadi_fn;

/* The table entry of the CasADi function f (an X-macro argument: see <P>_SOLVERS). */
#define BAL_CASADI_FN(f) {f, f##_incref, f##_checkout, f##_release, f##_decref},

#endif /* BAL_COMMON_H */
