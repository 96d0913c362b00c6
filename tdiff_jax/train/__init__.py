"""Training: optimiser, checkpoints, data setup and the training loop."""
