"""The package version (its own module, so that writers of files can stamp it without importing the package)."""

__version__ = "0.1.0"
