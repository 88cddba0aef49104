"""Training: typed recipes (``config``), the LightningModule (``module``), loggers and the ``train`` entry point.

Importing this package is cheap; Lightning is imported by ``module``, ``loggers`` and inside ``run.train`` only."""
