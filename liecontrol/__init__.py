"""liecontrol: the application layer (the ``liecontrol`` command, benchmarks, reproductions, reports)."""

from importlib import metadata as _metadata

__all__ = ["__version__"]

try:
    __version__ = _metadata.version("liecontrol")
except _metadata.PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0+unknown"
