"""How each metric is measured: timing loops, statistics, sizes, accuracy, environment."""
