"""Sound bounds over boxes: interval, Taylor-model and linear-relaxation enclosures of the
gain network and of D, and sound eigenvalue bounds. `certify.enclosures` re-exports them."""
