"""What the run time and the simulated rig share: the clock, the motion profile and the plant (HV stage + specimen).

The core depends on the physical models (:mod:`bench.models`) only — never on the drivers, the twins or the rest
of the application (tests/test_layers.py).
"""
