"""ripplecal service: identification methods, sweep plans and their runner, storage, LUT export,
scheduler, REST API and CLI."""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version

try:
    __version__ = _version("ripplecal")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"
