"""certify test suite."""
