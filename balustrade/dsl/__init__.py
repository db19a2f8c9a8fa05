"""The balustrade language: systems, sets, the horizon problem builder and cost terms."""

from balustrade.dsl.costs import Cost, Term, TermKind, max_of, norm, quad, squared_norm, sum_norms
from balustrade.dsl.joint import JointPolytope, joint_constraint
from balustrade.dsl.layout import Entry, Layout
from balustrade.dsl.ocp import OCP, Block, BlockKind, BlockTag, Parameter, Variable, VariableRole
from balustrade.dsl.policies import AffinePolicy
from balustrade.dsl.rates import input_rates, rate_cost, rate_limit
from balustrade.dsl.sets import Box, Ellipsoid, FunctionSet, Polytope, Set
from balustrade.dsl.system import LinearSystem, System
from balustrade.dsl.system_parametric import ParametricLinearSystem
from balustrade.dsl.tracking import tracking_cost

__all__ = [
    "OCP", "AffinePolicy", "Block", "BlockKind", "BlockTag", "Box", "Cost", "Ellipsoid",
    "Entry", "FunctionSet", "JointPolytope", "Layout", "LinearSystem", "ParametricLinearSystem",
    "Parameter", "Polytope", "Set", "System", "Term", "TermKind", "Variable", "VariableRole",
    "input_rates", "joint_constraint", "max_of", "norm", "quad", "rate_cost", "rate_limit",
    "squared_norm", "sum_norms", "tracking_cost",
]
