"""Adaptive meshing during a shot: form-factor gradients by autograd, refinement criteria,
the scheduler that picks and splits receivers, and carrying a hemicube's atlas over to the
children (relabelling) while a refining shot is redone."""
