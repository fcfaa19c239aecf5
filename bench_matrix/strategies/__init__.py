"""Training-aware strategies: trainers that fine-tune a source model before a backend converts it."""
