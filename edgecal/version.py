"""edgecal's version, in one place the package face, the CLI and the provenance of results all read.

Kept equal to ``project.version`` in pyproject.toml.
"""

__version__ = "0.1.0"
