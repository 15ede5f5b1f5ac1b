"""Evaluation of a prediction folder against references: metrics, uncertainty checks, reports and maps."""
