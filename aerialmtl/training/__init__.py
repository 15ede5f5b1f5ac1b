"""Training: the configuration, the trainer and its loop, losses, task weighting, several processes."""
