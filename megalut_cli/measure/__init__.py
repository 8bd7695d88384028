"""Feature measurement on stamps (paper Sect. 4).

:mod:`.features` measures stacks of stamps (HSM adaptive moments, ``skymad``, S/N,
flags); :mod:`.stamps` locates stamps in FITS images; :mod:`.measure` runs
``megalut measure`` on files, in parallel.
"""
