"""The thesis examples assembled: a model (:mod:`balustrade.models`) with the formulations,
syntheses and targets that make it a runnable setup — e.g. the bicycle's RPI set and terminal
CBF, the pendulum's compiled PCBF problems for sampling. Models import only the language;
whatever needs a formulation or a solver to build lives here, and the reproductions, the
sampler's registry (by name), benchmarks and tests use it.
"""
