"""The one place the software version is written: pyproject reads it, every log header and report carries it."""

__version__ = "0.1.0"


def software_version() -> str:
    """The provenance string logs and reports carry, e.g. "pilescan 0.1.0"."""
    return f"pilescan {__version__}"
