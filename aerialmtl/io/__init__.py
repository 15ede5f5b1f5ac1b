"""Rasters and vectors in and out: opening and aligning inputs, output folders, profiles, COGs, VRTs."""
