"""The package version, in one place: read by the build (pyproject.toml) and by code that must not import the
package's ``__init__`` to know it."""

__version__ = "0.1.0"
