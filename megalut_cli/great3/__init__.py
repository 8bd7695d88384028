"""GREAT3-format branches (Mandelbaum et al. 2014; paper Sect. 8).

:mod:`.layout` holds the file layout of a branch (names, galaxy IDs, text catalogs with
``# name`` header lines, star fields, the constant-shear submission file and the truth
files), :mod:`.sim` writes simulated branches in that layout (``megalut simulate
--great3 DIR``), :mod:`.evaluate` measures m, c and ``Q_c`` of a constant-shear
submission or per-galaxy predictions against a branch's truth, and :mod:`.pipeline` runs a
branch subfield by subfield (``megalut run`` on a pipeline file with a ``[branch]``
table). See ``docs/great3.md``.
"""
