"""Design tools solved as semidefinite programs: the metric, the LMI observers, and
LipSDP (the only package that imports cvxpy)."""
