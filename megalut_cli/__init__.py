"""megalut: weak-lensing shear measurement with machine learning (Tewes et al. 2019)."""

__version__ = "0.1.0"
#: Date written into generated man pages (kept fixed so that they are reproducible).
__release_date__ = "2026-11-21"

__all__ = ["__version__"]
