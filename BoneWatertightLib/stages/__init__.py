"""The pipeline's stages, in order (paper §2; each takes arrays and explicit keyword arguments):

1. :mod:`.prepare` - validate, crop, resample to the isotropic working grid
2. :mod:`.filtering` - the hybrid filter
3. :mod:`.threshold` - two-step thresholding with morphology, bone k apart from its neighbours
   (:mod:`.autothreshold` proposes H0/HT from the HU histogram)
4. :mod:`.visible` - visible points by hyper-spherical mapping
5. :mod:`.poisson` - the initial watertight surface M0
6. :mod:`.deform` - iterative Laplacian deformation
7. :mod:`.refine` - sub-voxel edge refinement (ours)

Volumes are (z, y, x) numpy arrays on the working grid; points are (n, 3) x-y-z "grid
millimetres" (voxel index * spacing), mapped to physical LPS by
:meth:`.prepare.Grid.grid_to_physical`.
"""
