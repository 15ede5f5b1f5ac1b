"""Helpers the tests share: tiny rasters, prediction and tile folders, tiny models, the CLI in-process."""
