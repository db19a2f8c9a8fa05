"""Offline design: solve the synthesis formulations of :mod:`balustrade.problems` (SDPs
written in the synthesis language) on a target and turn their solutions into the objects
the formulations and controllers use — terminal CBFs (6.17)/(7.11)
(:mod:`balustrade.design.terminal_cbf`) and ellipsoidal RPI sets (5.14)
(:mod:`balustrade.design.rpi`).

Layering: ``design`` may import ``backends``, ``problems`` and ``dsl``; ``problems`` never
imports ``design`` (a formulation names no solver).
"""
