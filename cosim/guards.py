"""The runner's guards a command runs without, said once in its output and in its reports.

Every step through ``CoupledSystem.step`` (`cosim run`, gradcheck, optimize, sweep and most benchmarks)
stops the run at a NaN or inf (NaN), a CFL number above ``time.cfl`` (CFL), particles, bodies or cloth leaving the grid
(domain), energy above the budget (energy budget, ``cosim.conservation``) and a rigid body gone
through (tunnelling). A command that turns some off, or times an engine stepped alone (none of them
run there), declares a ``GuardsOff``: ``announce`` prints its line, reports put it under their header
(``cosim.bench.report.report_header``) and CSVs in a ``guards_off`` column.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

ENERGY, TUNNELLING, CFL, NAN, DOMAIN = "energy budget", "tunnelling", "CFL", "NaN", "domain"
ENGINE_ALONE = (CFL, NAN, DOMAIN, ENERGY)  # an MPM engine stepped without ``CoupledSystem.step``


@dataclass(frozen=True)
class GuardsOff:
    """Guards a command runs without (``guards``, names above) and why."""

    guards: tuple[str, ...]
    why: str

    def line(self) -> str:
        """One line, e.g. "guards off: energy budget, tunnelling (measured, not enforced)"."""
        return f"guards off: {', '.join(self.guards)} ({self.why})"

    def column(self) -> str:
        """The ``guards_off`` value of a CSV row: the guards, ';'-separated."""
        return "; ".join(self.guards)


def announce(off: GuardsOff) -> str:
    """Print ``off``'s line (once per command: call it where the command starts); returns it."""
    print(off.line(), flush=True)
    return off.line()


def measure_only(sim) -> None:
    """Turn the energy budget and the tunnelling stop of ``sim`` (a ``CoupledSystem``) into measurements:
    the excess and the particles through walls are still recorded, no run stops on them."""
    sim.guard.conservation.share = sim.guard.tunnel_share = math.inf
