"""The installed distribution's version (one place; read with importlib.metadata)."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("iptm")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
