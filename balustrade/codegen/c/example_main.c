/* main.c: closed loop of an emitted PCBF safety filter on its model, all in C (written by
 * balustrade.codegen.write_example). example.h (generated) names the filter (BAL_STEP,
 * its header) and holds the example's data: N_INIT initial states X_INIT, STEPS steps per
 * closed loop, the constant proposal U_PROP.
 * Usage: ./main [n_timing]  (n_timing control steps are timed; default 2000). Prints the
 * trajectories, then lines "BENCH <name> <value>".
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "example.h"

static const casadi_real x_init[N_INIT][BAL_QX(NX)] = X_INIT;
static const casadi_real u_prop[BAL_QX(NU)] = U_PROP;

static double now(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double) ts.tv_sec + 1e-9 * (double) ts.tv_nsec;
}

static int cmp_double(const void* a, const void* b) {
  double x = *(const double*) a, y = *(const double*) b;
  return (x > y) - (x < y);
}

static double median(double* v, int n) {
  qsort(v, (size_t) n, sizeof(double), cmp_double);
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/* The plant x+ = f(x, u) (the emitted dynamics <name>_dynamics, w = 0, theta = 0). */
static const casadi_real* dyn_arg[BAL_QX(dynamics_SZ_ARG)];
static casadi_real* dyn_res[BAL_QX(dynamics_SZ_RES)];
static casadi_int dyn_iw[BAL_QX(dynamics_SZ_IW) + 1];
static casadi_real dyn_w[BAL_QX(dynamics_SZ_W) + 1];
static const casadi_real zeros[16] = {0};

static int plant(int mem, const casadi_real* x, const casadi_real* u, casadi_real* x_next) {
  dyn_arg[0] = x;
  dyn_arg[1] = u;
  dyn_arg[2] = zeros;
  dyn_arg[3] = zeros;
  dyn_res[0] = x_next;
  return BAL_QX(dynamics)(dyn_arg, dyn_res, dyn_iw, dyn_w, mem);
}

int main(int argc, char* argv[]) {
  int n_timing = argc > 1 ? atoi(argv[1]) : 2000;
  int i, j, k, status, mem, n_dyn_blocks = 200, n_fallback = 0;
  casadi_real x[BAL_QX(NX)], x_next[BAL_QX(NX)], u[BAL_QX(NU)], h;
  double t0, *times;
  BAL_QX(work)* wk = BAL_QX(alloc)();
  if (!wk) {
    fprintf(stderr, "the filter's alloc failed\n");
    return 1;
  }
  BAL_QX(dynamics_incref)();
  mem = BAL_QX(dynamics_checkout)();
  if (n_timing < 1) n_timing = 1;
  times = (double*) malloc(sizeof(double)
                           * (size_t) (n_timing > n_dyn_blocks ? n_timing : n_dyn_blocks));
  if (!times) return 1;
  /* closed loops from a few initial states, proposal u_p = const */
  for (j = 0; j < N_INIT; ++j) {
    BAL_QX(reset)(wk);
    for (i = 0; i < BAL_QX(NX); ++i) x[i] = x_init[j][i];
    printf("# closed loop %d: k, x[0..%d], u[0..%d], h_PB, status\n", j, BAL_QX(NX) - 1,
           BAL_QX(NU) - 1);
    for (k = 0; k < STEPS; ++k) {
      BAL_QX(step)(x, u_prop, u, &h, &status, wk);
      n_fallback += status != BAL_PCBF_OK;
      printf("%d", k);
      for (i = 0; i < BAL_QX(NX); ++i) printf(" % .6f", x[i]);
      for (i = 0; i < BAL_QX(NU); ++i) printf(" % .6f", u[i]);
      printf(" %.6g %d\n", h, status);
      if (plant(mem, x, u, x_next)) return 1;
      for (i = 0; i < BAL_QX(NX); ++i) x[i] = x_next[i];
    }
  }
  /* timing: one control step (both problems), along the same closed loops */
  for (k = 0; k < n_timing; ++k) {
    if (k % STEPS == 0) {
      BAL_QX(reset)(wk);
      for (i = 0; i < BAL_QX(NX); ++i) x[i] = x_init[(k / STEPS) % N_INIT][i];
    }
    t0 = now();
    BAL_QX(step)(x, u_prop, u, &h, &status, wk);
    times[k] = now() - t0;
    if (plant(mem, x, u, x_next)) return 1;
    for (i = 0; i < BAL_QX(NX); ++i) x[i] = x_next[i];
  }
  printf("BENCH pcbf_step_median_us %.4f\n", 1e6 * median(times, n_timing));
  /* timing: the dynamics, in blocks of 1000 calls */
  for (j = 0; j < n_dyn_blocks; ++j) {
    t0 = now();
    for (k = 0; k < 1000; ++k) {
      if (plant(mem, x, u, x_next)) return 1;
      x[0] = x_next[0] * 0.5;
    }
    times[j] = (now() - t0) / 1000.0;
  }
  printf("BENCH dynamics_median_ns %.4f\n", 1e9 * median(times, n_dyn_blocks));
  printf("BENCH fallbacks %d\n", n_fallback);
  free(times);
  BAL_QX(dynamics_release)(mem);
  BAL_QX(dynamics_decref)();
  BAL_QX(free)(wk);
  return 0;
}
