"""The sim's physics as the tests that do not depend on its fidelity run it: at 120 Hz, half the
default 240 Hz (services/sim/config.py), and with the solver's default passes. 20 passes a step
instead of 50 (`[sim] solver_iterations`) took about a quarter off a pick and place's physics and the
tours' sim 80 CPU-s instead of 88, but nothing measurable off the parallel part (268.2 s and 443.4
CPU-s against 268.5 s and 445.1, 2026-11-28), and a CI run with it then saw an arm trajectory's
first point 0.116 rad from the joint states recorded before it (test_system's recheck). The robot
contract's and the wall-clock tests' sims run the defaults."""

from __future__ import annotations

FAST_PHYSICS_HZ = 120.0
# The same as a `[sim]` table's line, for a stack's config file.
FAST_SIM = f"physics_hz = {FAST_PHYSICS_HZ}\n"
