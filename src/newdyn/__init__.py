"""newdyn: find new dynamics in machines by Bayesian calibration of a physics model."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("newdyn")
except PackageNotFoundError:  # running from a source tree that was not pip-installed
    __version__ = "0+unknown"
