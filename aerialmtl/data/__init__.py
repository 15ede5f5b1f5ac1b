"""Torch datasets over tile folders: patches, the decoded patch cache, batches and augmentations; synthetic scenes."""
