"""The library's version, ``fsof_torch.__version__``, in a module of its own: the library's modules
that record it (:mod:`fsof_torch.io.provenance`) read it here without importing the package."""

__version__ = "0.1.0"
