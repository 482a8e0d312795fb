"""texspace service package: HTTP API, database, storage and job queue."""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("texspace")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0"
