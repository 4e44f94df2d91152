"""pilescan payload firmware: runs on the companion computer and, unchanged, in the SITL.

`firmware_py.core` holds the contracts the payload, the SITL and the ground station share; the rest
of the package is the drone program.
"""

from firmware_py.core.version import __version__

__all__ = ["__version__"]
