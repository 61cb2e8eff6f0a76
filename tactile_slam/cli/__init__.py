"""Command-line interface (``tactile-slam``)."""
