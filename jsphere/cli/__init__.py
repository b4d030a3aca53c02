"""The `jsphere` command line."""

from .app import console as console, main as main
