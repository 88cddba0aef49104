"""Where a closed-loop run's settings depart from the paper (and from the authors' code): ``departures``, the
sentences every report lists under its table, gathered from the settings and from the registry entries they name
(``TerminalTerm.departures``, ``RTGFeed.departures``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ttompc.mpc.rtg import RTG_MODES
from ttompc.mpc.settings import MPCSettings
from ttompc.mpc.terminal import TERMINALS

if TYPE_CHECKING:
    from ttompc.scenarios.base import Scenario


def departures(settings: MPCSettings, scenario: Scenario) -> list[str]:
    """The settings of a run on ``scenario`` that depart from the paper (and from the authors' code), one sentence
    each: the terminal term's (``TerminalTerm.departures``), the loop's and the rtg mode's (``RTGFeed.departures``)."""
    out = TERMINALS[settings.terminal].departures(settings, scenario)
    end_horizon = settings.end_horizon_on(scenario)
    if end_horizon > 0:
        out.append(
            f"shrinking end horizon: windows run to N once N − t <= {end_horizon} (the paper keeps H and "
            "truncates the windows at N)"
        )
    if settings.end_shift:
        out.append(
            "shifted end start: the learned methods' windows that reach the end start from the previous plan's "
            "tail where that plan reached the end too (the paper warm-starts every window from its method)"
        )
    out += RTG_MODES[settings.rtg_mode].departures()
    if settings.mode != "soft":
        out.append(f"{settings.mode} end condition (the paper's analyses: soft)")
    rti = settings.rti_scope(scenario)
    if rti:
        whose = {
            "model": "the learned methods' windows (the baselines converge)",
            "end": "the learned methods' windows that reach the end (the rest converge)",
        }.get(str(rti), "every window")
        out.append(
            f"real-time iteration in {whose}: one SCP subproblem per MPC step from the previous solution shifted (the "
            "paper solves every window to convergence)"
        )
    if settings.decode_every > 1:
        out.append(
            f"decode every {settings.decode_every} steps: TTO-MPC's windows in between are slices of the last decoded "
            "plan (the paper decodes at every step)"
        )
    return out
