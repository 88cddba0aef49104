"""The evaluation protocol (docs/evaluation.md): seeded held-out problems (``problems``), open-loop warm starts
(``warmstart``), the closed-loop study on nominal and perturbed plants (``closed_loop``), their metrics
(``metrics``; per-episode closed-loop metrics live next to the MPC loop in ``ttompc.mpc.metrics``), reports and
plots. Submodules are imported on use (they pull in solvers and torch)."""
