"""Tissue mechanics of the preop model: closed surfaces, the tetrahedral mesher and linear FEM."""
