/* Replays the C steps recorded by benchmarks/rapsf_hot_c.py through the emitted hot-started
 * RAPSF step (module rh in the same folder) and times each call: wall (CLOCK_MONOTONIC) and
 * CPU (CLOCK_PROCESS_CPUTIME_ID). Usage: rapsf_hot_c <recorded.bin> <out.bin>
 * recorded: int64 steps, nx, nu, nth_len, s_len; per step x, u_p, theta, s, falsified
 * (doubles). out: per step wall ms, cpu ms, status, u (nu doubles). */
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "rh.h"

static double now(clockid_t c) {
  struct timespec t;
  clock_gettime(c, &t);
  return (double) t.tv_sec + 1e-9 * (double) t.tv_nsec;
}

int main(int argc, char** argv) {
  long long hd[5];
  int k, st, bad = 0;
  FILE *in, *out;
  double *x, *up, *th, *s, *u, fals, w0, c0, rec[3];
  rh_work* wk;
  if (argc < 3) return 2;
  in = fopen(argv[1], "rb");
  out = fopen(argv[2], "wb");
  if (!in || !out || fread(hd, sizeof(long long), 5, in) != 5) return 3;
  x = malloc(hd[1] * sizeof(double));
  up = malloc(hd[2] * sizeof(double));
  th = malloc(hd[3] * sizeof(double));
  s = malloc(hd[4] * sizeof(double));
  u = malloc(hd[2] * sizeof(double));
  wk = rh_alloc();
  if (!x || !up || !th || !s || !u || !wk) return 4;
  for (k = 0; k < hd[0]; ++k) {
    if (fread(x, sizeof(double), hd[1], in) != (size_t) hd[1] ||
        fread(up, sizeof(double), hd[2], in) != (size_t) hd[2] ||
        fread(th, sizeof(double), hd[3], in) != (size_t) hd[3] ||
        fread(s, sizeof(double), hd[4], in) != (size_t) hd[4] ||
        fread(&fals, sizeof(double), 1, in) != 1) return 5;
    w0 = now(CLOCK_MONOTONIC);
    c0 = now(CLOCK_PROCESS_CPUTIME_ID);
    rh_step(x, up, th, s, fals != 0.0, u, &st, wk);
    rec[1] = (now(CLOCK_PROCESS_CPUTIME_ID) - c0) * 1e3;
    rec[0] = (now(CLOCK_MONOTONIC) - w0) * 1e3;
    rec[2] = st;
    bad += fwrite(rec, sizeof(double), 3, out) != 3;
    bad += fwrite(u, sizeof(double), hd[2], out) != (size_t) hd[2];
  }
  rh_free(wk);
  free(x); free(up); free(th); free(s); free(u);
  fclose(in);
  fclose(out);
  return bad != 0;
}
