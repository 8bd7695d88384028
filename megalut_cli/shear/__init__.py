"""Shear estimates: applying a trained model (:mod:`.predict`) and measuring biases.

:mod:`.bias` holds the linear bias model (paper Eq. 2), the PSF-frame rotation and the
GREAT3 ``Q_c`` metric; :mod:`.conditional` the equal-population binning; :mod:`.evaluate`
the catalog-level analysis behind ``megalut evaluate``; :mod:`.plots` its figures.
"""
