"""The proofs: the MPDI decision and the proved rate, and the side proofs (residual,
dk/dy, the manifold quantity)."""
