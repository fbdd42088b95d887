"""In silico liver phantoms: procedural anatomy, tetrahedral FEM deformation, target crops, datasets.

Pipeline (one liver = one integer seed, every random stream derived from indices only):

1. anatomy.make_liver(seed): implicit anatomical shape -> marching cubes (2.2 mm grid) ->
   Taubin smoothing -> random anisotropic scaling to 145-215 x 85-125 x 105-165 mm
   (width x depth x height). Closed and watertight, ~2 mm edges, RAS frame (+x patient right,
   +y anterior, +z superior). docs/livers_grid.png shows 12 of them (scripts/render_livers.py).
2. tetmesh.build_tetmesh: a regular grid of cubes covering the liver split into 6 Kuhn
   tetrahedra (~11k tets, ~2.5k nodes); the surface is embedded (exact barycentric weights).
   Interior nodes (>= 2 mm inside) are the fiducials (up to 300, fixed order).
3. fem: small-strain linear elasticity (scikit-fem, nu = 0.45) with a random posterior support
   patch and 1-3 random pressing surface patches plus a weak body force, made self-equilibrated;
   the infinitesimal rigid part is subtracted, then the load is scaled so that the fiducial RMS
   after Procrustes on all volumetric vertices follows a gamma law (mean 3.37 mm, <= 11.5 mm).
   Not neo-Hookean: a vectorized neo-Hookean Newton solver was tried and needed 17-30 s per
   deformation (load stepping), far over the 5 s budget; the equilibrated loads keep rotations
   small, where the linear model is accurate.
4. crop.make_target: fresh area-uniform resampling of the deformed surface, a crop to the
   requested visibility M/N (preprocess.py's normalization and 0.04 voxels, measured on the
   final target) by bisection, `random` (geodesic patch) or `camera` (70-degree laparoscope at
   80-150 mm on the anterior side, z-buffer hidden-point removal), a uniform SO(3) rotation, a
   translation in [-100, 100] mm per axis, and uniform noise [-0.5, 0.5] x level mm.
5. dataset / testset / loader: case NPZs + manifest.csv (`liver-p2p dataset generate --out`),
   named test sets (`--testset insilico-test-v1`, `insilico-camera-v1`, `insilico-smoke`) and
   validation sets (`insilico-val-v1`, `insilico-val-camera-v1`: for choosing defaults, so the
   test sets stay unseen) on liver seeds 900-999, never used for training, and a training store for PairSampler
   (`liver-p2p dataset generate --store DIR --livers N --deformations D --seed S`).
"""
