"""What is certified: the gain network, its one propagation over any arithmetic, the
activations with their sound rules, the verification problem, checkpoints and
importers of networks trained elsewhere."""
