"""Readers and writers for the file formats users have (PLY variants, posed-image datasets, our container)."""
