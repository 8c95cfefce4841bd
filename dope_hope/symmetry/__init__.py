"""Object symmetries, one owner for every use.

- :mod:`~dope_hope.symmetry.transforms`: what the BOP symmetry fields and the HOPE
  categories mean as model-frame transforms (the BOP toolkit's discretization included).
- :mod:`~dope_hope.symmetry.resolve`: which symmetries an object has (the one resolution
  order of training labels, ``dope-hope demo`` and the evaluation).
- :mod:`~dope_hope.symmetry.labels`: symmetry-aware keypoint labels (one canonical corner
  order per view).

Declaration files are read by :mod:`dope_hope.io.symmetries`, the BOP fields by
:func:`dope_hope.io.bop.parse_symmetries`.
"""
