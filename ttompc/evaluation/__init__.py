"""Evaluations of trained planners: open-loop warm starts (``warmstart``), the closed-loop planning-horizon study
(``horizon``), their metrics, reports and plots. Submodules are imported on use (they pull in solvers and torch)."""
