"""Simulation of plant and observer: the batched integrator and where runs start."""
