"""Front ends and their shared service: :mod:`.run` (one case -> files + report), :mod:`.cli`
(``bonewatertight`` / ``python -m BoneWatertightLib``), :mod:`.batch` (many cases, local
processes or Dask), :mod:`.render` (PNG pictures, VTK offscreen), :mod:`.options` (command-line
options derived from the parameter schema)."""
