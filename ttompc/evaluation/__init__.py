"""The evaluation protocol (docs/evaluation.md): seeded held-out problems (``problems``), open-loop warm starts
(``warmstart``), the closed-loop study on nominal and perturbed plants (``closed_loop``), the closed-loop metrics of
MPC episodes (``episodes``), report metrics (``metrics``) and their bootstrap statistics (``stats``), reports and
plots. Submodules are imported on use (they pull in solvers and torch)."""
