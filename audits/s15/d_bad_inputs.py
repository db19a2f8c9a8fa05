"""Audit D: bad inputs to the §8.2/§8.3 public functions: each must give a BalustradeError
naming the argument (or a recorded fallback in a loop), never another exception."""
import os

os.makedirs("/tmp/audit_d", exist_ok=True)  # scratch files of the audit D scripts
import numpy as np

from balustrade.errors import BalustradeError


def probe(label, fn):
    try:
        out = fn()
        print(f"[no error] {label}: {str(out)[:100]!r}")
    except BalustradeError as e:
        print(f"[ok BalustradeError] {label}: {str(e)[:110]}")
    except BaseException as e:
        print(f"[CRASH {type(e).__name__}] {label}: {str(e)[:110]}")

import balustrade.reproduce.lane_change as lc
import balustrade.reproduce.obstacles as ob
from balustrade.design import incremental_rpi as ir
from balustrade.examples.bicycle import bicycle_design
from balustrade.models import bicycle as bc
from balustrade.models import obstacle_car as oc
from balustrade.problems.obstacles import naive_mpc_problem

probe("signed_distance (n,1) positions", lambda: oc.signed_distance(np.zeros((3, 1))))
probe("signed_distance NaN", lambda: oc.signed_distance(np.full((1, 5), np.nan)))
probe("signed_distance obstacles shape (9,2)", lambda: oc.signed_distance(np.zeros((1, 5)), np.zeros((9, 2))))
probe("symmetries (n,3)", lambda: oc.symmetries(np.zeros((2, 3))))
probe("constraint_set obstacles (9,2)", lambda: oc.constraint_set(np.zeros((9, 2))).c(np.zeros(5)))
probe("obstacle_car ts=-1", lambda: oc.obstacle_car(ts=-1.0))
probe("ObstacleSetup(N=0).deltas", lambda: oc.ObstacleSetup(N=0).deltas)
probe("initial_state((5, 5)) outside arena", lambda: ob.initial_state((5.0, 5.0)))
probe("initial_state((nan, 0))", lambda: ob.initial_state((np.nan, 0.0)))
probe("initial_state((1,))", lambda: ob.initial_state((1.0,)))
probe("naive_mpc_problem position=(0, 9)", lambda: naive_mpc_problem(oc.obstacle_car(), oc.obstacle_setup().U, position=(0, 9)))
probe("naive_mpc_problem horizon=0", lambda: naive_mpc_problem(oc.obstacle_car(), oc.obstacle_setup().U, horizon=0))
probe("pcbf_algorithm(horizon=0)", lambda: ob.pcbf_algorithm(horizon=0))
probe("path_of(None)", lambda: ob.path_of(None))
probe("bicycle(ts=0)", lambda: bc.bicycle(ts=0.0))
probe("bicycle(wheelbase=-1)", lambda: bc.bicycle(wheelbase=-1.0))
probe("jacobian_ldi lb (3,)", lambda: bc.jacobian_ldi(np.zeros(3), np.ones(3)))
probe("jacobian_ldi v nan", lambda: bc.jacobian_ldi([0, 0, np.nan, 0], [0, 0, 1, 0]))
probe("jacobian_ldi ts=-1", lambda: bc.jacobian_ldi([0, -.1, .5, -.1], [0, .1, 1, .1], ts=-1.0))
probe("bicycle_design(N=0)", lambda: bicycle_design(N=0))
probe("bicycle_design(delta_step=-1)", lambda: bicycle_design(delta_step=-1.0))
probe("bicycle_design(delta_step=nan)", lambda: bicycle_design(delta_step=float('nan')))
probe("bicycle_design(N=2.5)", lambda: bicycle_design(N=2.5))
d = bicycle_design(N=20, delta_step=1e-3)
probe("ShiftedCBF((3,))", lambda: d.cbf(np.zeros(3)))
probe("ShiftedCBF(nan)", lambda: d.cbf(np.full(4, np.nan)))
probe("sampled_rpi_check samples=0", lambda: ir.sampled_rpi_check(d.system, d.error, d.X, d.U_E, d.W, samples=0))
probe("sampled_rpi_check samples=-5", lambda: ir.sampled_rpi_check(d.system, d.error, d.X, d.U_E, d.W, samples=-5))
probe("sampled_rpi_check Z wrong dim", lambda: ir.sampled_rpi_check(d.system, d.error, d.U, d.U_E, d.W, samples=10))
probe("sampled_terminal_check samples=0", lambda: ir.sampled_terminal_check(d.system, d.terminal_spec(), samples=0))
probe("worst_case_rpi_check starts=0", lambda: ir.worst_case_rpi_check(d.system, d.error, d.X, d.U_E, d.W, starts=0))
probe("incremental_rpi lambdas=[]", lambda: ir.incremental_rpi(d.ldi, d.W, d.X, d.U, np.zeros((4, 1)), np.zeros(4), lambdas=[]))
probe("incremental_rpi G (3,1)", lambda: ir.incremental_rpi(d.ldi, d.W, d.X, d.U, np.zeros((3, 1)), np.array([0, 0, 1.1, 0]), lambdas=[0.9]))
probe("lateral_acceleration (4,)", lambda: lc.lateral_acceleration(np.zeros(4)))
probe("human (2,)", lambda: lc.human(np.zeros(2)))
probe("config('x')", lambda: lc.config("x"))
probe("lane main --seeds 0", lambda: lc.main(["--out", "/tmp/audit_d/x", "--seeds", "0"]))
ctr = lc.controllers(d, rho=0.5)
for name, c in ctr.items():
    probe(f"{name}.step NaN x", lambda c=c: c.step(np.full(4, np.nan), np.zeros(2))[1].status)
    probe(f"{name}.step x (3,)", lambda c=c: c.step(np.zeros(3), np.zeros(2)))
    probe(f"{name}.step u_p (3,)", lambda c=c: c.step(np.array([0.4, 0, 1.1, 0]), np.zeros(3)))
    probe(f"{name}.step NaN u_p", lambda c=c: c.step(np.array([0.4, 0, 1.1, 0]), np.full(2, np.nan))[1].status)
    c.reset()
    probe(f"{name}.step far x (p_y=50, v=5)", lambda c=c: (lambda r: (r[0], r[1].status, r[1].fallback, r[1].values.get('h_r')))(c.step(np.array([50.0, 0, 5.0, 0]), np.zeros(2))))
