"""The balustrade language: systems, sets, the horizon problem builder and cost terms."""

from balustrade.dsl.costs import Cost, max_of, norm, quad, squared_norm, sum_norms
from balustrade.dsl.ocp import OCP, Block, Parameter, Variable
from balustrade.dsl.rates import input_rates, rate_cost, rate_limit
from balustrade.dsl.sets import Box, Ellipsoid, FunctionSet, Polytope, Set
from balustrade.dsl.system import LinearSystem, System
from balustrade.dsl.tracking import tracking_cost

__all__ = [
    "OCP", "Block", "Box", "Cost", "Ellipsoid", "FunctionSet", "LinearSystem", "Parameter",
    "Polytope", "Set", "System", "Variable", "input_rates", "max_of", "norm", "quad",
    "rate_cost", "rate_limit", "squared_norm", "sum_norms", "tracking_cost",
]
