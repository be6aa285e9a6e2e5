"""Sound arithmetic: intervals with directed rounding, interval helpers, eigenvalue
bounds of interval matrices, batched linear algebra and the device rules."""
