"""Fluids on meshes: the CFD ground truth (geometry, FEM, solver, datasets) and the
MeshGraphNet (model, training, evaluation, figures)."""
