"""Training: typed recipes (``config``), the LightningModule (``module``), loggers, the ``train`` entry point and
the training objective by split (``fit_loss``, ``ttompc evaluate loss``).

Importing this package is cheap; Lightning is imported by ``module``, ``loggers`` and inside ``run.train`` only."""
