"""Moved to :mod:`balustrade.backends.passes.classify` (the cvxpy chain's first pass); this
name re-exports it for code written before."""

from balustrade.backends.passes.classify import (  # noqa: F401
    Affine,
    JointQuadratic,
    Quadratic,
    affine,
    joint_quadratic,
    psd_factor,
    quadratic,
)
