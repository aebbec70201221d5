"""The package version (``jaxmpm.__version__``; the HDF5 files record it)."""

__version__ = "0.1.0"
