"""Front ends and their shared service: :mod:`.run` (the run service: one case or several bones
-> files + report, and the one call of the pipeline every front end makes), :mod:`.cli`
(``bonewatertight`` / ``python -m BoneWatertightLib``), :mod:`.batch` (many cases, local
processes or Dask), :mod:`.render` (PNG pictures, VTK offscreen), :mod:`.options` (command-line
options derived from the parameter schema); for 3D Slicer, :mod:`.nodes` (the run service on
MRML nodes, in this process or in a child process), :mod:`.child` (a run in a child process),
:mod:`.preview` (the panel's threshold preview), :mod:`.summaries` (its result lines) and
:mod:`.slicer_support` (the panel's Qt-free decisions). Only :mod:`BoneWatertightLib.mrml`
imports ``slicer``; the modules here use it."""
