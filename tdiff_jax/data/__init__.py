"""AV2 reading, synthetic AV2 worlds, the preprocessing cache and batches."""
