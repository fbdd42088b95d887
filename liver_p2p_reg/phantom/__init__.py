"""In silico liver phantoms: procedural anatomy, tetrahedral FEM deformation, target crops, datasets."""
