"""GREAT3-format branches (Mandelbaum et al. 2014; paper Sect. 8).

:mod:`.layout` holds the file layout of a branch (names, galaxy IDs, text catalogs with
``# name`` header lines, star fields, the constant-shear submission file and the truth
files), :mod:`.sim` writes simulated branches in that layout (``megalut simulate
--great3 DIR``), :mod:`.evaluate` measures m, c and ``Q_c`` of a constant-shear
submission or per-galaxy predictions against a branch's truth. The branch pipeline of
``megalut run`` (a pipeline file with a ``[branch]`` table, run subfield by subfield) is
:mod:`megalut_cli.pipeline.great3_file` and :mod:`megalut_cli.pipeline.great3_run`. See
``docs/great3.md``.
"""
