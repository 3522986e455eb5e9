"""Implementations of the ``mlv-ros`` subcommands (one module each)."""
