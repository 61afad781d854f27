"""liecontrol: the application layer (the ``liecontrol`` command, benchmarks, reproductions, reports)."""

__all__ = ["__version__"]
__version__ = "0.1.0"
