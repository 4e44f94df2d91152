"""pilescan payload firmware: runs on the companion computer and, unchanged, in the SITL."""

__version__ = "0.1.0"
