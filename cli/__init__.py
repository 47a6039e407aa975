"""Command-line interface (thin click layer over the library API)."""
