"""The verifier checks: one `check_x(problem, ...) -> XResult` per module."""
