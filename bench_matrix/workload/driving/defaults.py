"""The built-in driving datasets as the matrix format offers them: names, tasks (the first dataset is the
default) and what they hold, and the [v, w] label normalisation of the regression one."""

TASKS = {"driving": "regression", "driving_bends": "classification"}
DEFAULT_DATASET = next(iter(TASKS))
DESCRIPTION = ("driving: road images labelled [v, w] (regression); driving_bends: the same images labelled "
               "by the bend ahead (5 classes)")
SPEED_LABELS = {"columns": ("v", "w"), "offset": (6.5, -7.1), "scale": (17.5, 14.2)}
