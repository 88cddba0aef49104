"""The evaluation protocol (docs/evaluation.md): seeded held-out problems (``problems``), open-loop warm starts
(``warmstart``), the closed-loop measurement (``measurement``), its study on nominal and perturbed plants
(``closed_loop``) and report (``closed_loop_report``), the closed-loop metrics of MPC episodes (``episodes``), report
metrics (``metrics``) and their bootstrap statistics (``stats``), and plots (``plots``). Submodules are imported on
use (they pull in solvers and torch)."""
