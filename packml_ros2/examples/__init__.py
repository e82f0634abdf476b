"""Example equipment modules to copy from."""
