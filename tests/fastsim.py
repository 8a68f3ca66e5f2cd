"""The sim's physics as the tests that do not depend on its fidelity run it: at 120 Hz and with 20
solver passes a step, against 240 Hz and 50 by default (services/sim/config.py). The tests' stacks
are CPU-bound on two cores (tests/suite.py), most of it the sims' physics. Measured on 2026-11-27:
the unit tests' pick and place took 1.58 to 1.66 s of CPU with 20 passes, 1.83 to 2.31 s with 50; the
tours' sim (tests/integration/test_tours.py) 80 CPU-s instead of 88. The robot contract's and the
wall-clock tests' sims keep the defaults."""

from __future__ import annotations

FAST_PHYSICS_HZ = 120.0
FAST_SOLVER_ITERATIONS = 20
# The same as a `[sim]` table's lines, for a stack's config file.
FAST_SIM = f"physics_hz = {FAST_PHYSICS_HZ}\nsolver_iterations = {FAST_SOLVER_ITERATIONS}\n"
