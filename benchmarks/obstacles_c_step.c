/* The emitted Algorithm 7.5 step of the obstacle car (benchmarks/obstacles_c_step.py), timed
 * inside C with clock_gettime: per path of the step and per part, warm (the same step
 * repeated, code and data in the caches) and cold (64 MB written between calls, so the
 * step's code and constants come from memory, as in a loop that does other work between
 * control steps). Compiled with the emitter's flags against the emitted obs.c (included, so
 * the static parts of bal/approx.c can be timed alone) and obs_casadi.c.
 *
 *   driver STEPS_FILE REPS   (a line per step: x[obs_NX] u_p[obs_NU])
 *
 * Prints "key value" lines: the median per path (warm, cold), the parts, and "u i u0 u1
 * status" for every step (the inputs the step chose, to compare with the library).
 */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "obs.c"

#define MAX_STEPS 4096
#define FLUSH_BYTES (64u << 20)

static double now_us(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return 1e6 * (double) t.tv_sec + 1e-3 * (double) t.tv_nsec;
}

static int by_value(const void* a, const void* b) {
  double d = *(const double*) a - *(const double*) b;
  return d < 0 ? -1 : d > 0;
}

static double median(double* v, int n) {
  if (n == 0) return NAN;
  qsort(v, (size_t) n, sizeof(double), by_value);
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

static volatile unsigned char* junk;
static void flush_caches(void) {
  size_t i;
  for (i = 0; i < FLUSH_BYTES; i += 64) junk[i]++;
}

static double X[MAX_STEPS][obs_NX], P[MAX_STEPS][obs_NU];
static double t_path[2][3][MAX_STEPS]; /* [warm, cold][certified, kept, both][step] */
static double t_part[4][MAX_STEPS];   /* h_next, screening, one (7.6), one (7.5) */

static int path_of(int status) {
  return status == BAL_APPROX_CERTIFIED ? 0 : status == BAL_APPROX_PROPOSAL_FEASIBLE ? 1 : 2;
}

int main(int argc, char** argv) {
  static const char* paths[3] = {"certified", "kept", "both"};
  static const char* parts[4] = {"h_next", "screening", "dec_solve", "filter_solve"};
  int n = 0, reps, i, j, k, mode, st = 0, pth, n_path[2][3] = {{0}}, n_part[4] = {0};
  double u[obs_NU], h, r[256], t0;
  FILE* f;
  obs_work* wk;
  if (argc < 3 || !(f = fopen(argv[1], "r"))) {
    fprintf(stderr, "usage: %s STEPS_FILE REPS\n", argv[0]);
    return 2;
  }
  reps = atoi(argv[2]);
  if (reps < 1 || reps > 256) reps = 11;
  while (n < MAX_STEPS) {
    for (j = 0; j < obs_NX; ++j) if (fscanf(f, "%lf", &X[n][j]) != 1) goto done;
    for (j = 0; j < obs_NU; ++j) if (fscanf(f, "%lf", &P[n][j]) != 1) goto done;
    ++n;
  }
done:
  fclose(f);
  junk = calloc(FLUSH_BYTES, 1);
  wk = obs_alloc();
  if (!junk || !wk) return 1;
  for (i = 0; i < n; ++i) {
    for (mode = 0; mode < 2; ++mode) {
      for (k = 0; k < reps; ++k) {
        if (mode) flush_caches();
        t0 = now_us();
        obs_step(X[i], P[i], u, &h, &st, wk);
        r[k] = now_us() - t0;
      }
      pth = path_of(st);
      t_path[mode][pth][n_path[mode][pth]++] = median(r, reps);
    }
    printf("u %d %.17g %.17g %d\n", i, u[0], u[obs_NU - 1], st);
    /* the parts, warm, at this step's (x, u_p) */
    for (k = 0; k < reps; ++k) {
      t0 = now_us();
      obs_value_h_next(wk, X[i], P[i]);
      r[k] = now_us() - t0;
    }
    t_part[0][n_part[0]++] = median(r, reps);
    if (pth == 0) continue;
    for (k = 0; k < reps; ++k) { /* h^(x) and the screened multi-start (7.6) */
      t0 = now_us();
      wk->h_up_ready = 0;
      wk->h_x = obs_value_h(wk, X[i]);
      obs_max_decrease(wk, X[i], wk->u_p);
      r[k] = now_us() - t0;
    }
    t_part[1][n_part[1]++] = median(r, reps);
    for (j = 0; j < obs_NX; ++j) wk->p_dec[obs_dec_P_x0 + j] = X[i][j];
    for (k = 0; k < reps; ++k) { /* one local (7.6) solve from the best screened start */
      t0 = now_us();
      obs_dec_cold_start(&wk->dec);
      for (j = 0; j < obs_NU; ++j) wk->dec.x0[obs_dec_W_u + j] = wk->best_u[j];
      obs_dec_solve(&wk->dec, wk->p_dec);
      r[k] = now_us() - t0;
    }
    t_part[2][n_part[2]++] = median(r, reps);
    if (pth == 1) continue;
    for (j = 0; j < obs_NX; ++j) wk->p_filter[obs_filter_P_x0 + j] = X[i][j];
    for (j = 0; j < obs_NU; ++j) wk->p_filter[obs_filter_P_u_p + j] = wk->u_p[j];
    wk->p_filter[obs_filter_P_dh] = wk->h_x - wk->best_v;
    wk->p_filter[obs_filter_P_rho] = obs_RHO;
    for (k = 0; k < reps; ++k) { /* one (7.5) solve from the (7.6) minimizer */
      t0 = now_us();
      obs_filter_cold_start(&wk->filter);
      for (j = 0; j < obs_NU; ++j) wk->filter.x0[obs_filter_W_u + j] = wk->best_u[j];
      obs_filter_solve(&wk->filter, wk->p_filter);
      r[k] = now_us() - t0;
    }
    t_part[3][n_part[3]++] = median(r, reps);
  }
  for (mode = 0; mode < 2; ++mode) {
    for (pth = 0; pth < 3; ++pth) {
      printf("path %s %s %d %.3f\n", mode ? "cold" : "warm", paths[pth], n_path[mode][pth],
             median(t_path[mode][pth], n_path[mode][pth]));
    }
  }
  for (k = 0; k < 4; ++k) printf("part %s %d %.3f\n", parts[k], n_part[k], median(t_part[k], n_part[k]));
  printf("candidates %d\n", obs_NC);
  obs_free(wk);
  free((void*) junk);
  return 0;
}
