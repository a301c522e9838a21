"""`bench benchmark`: the integrators (main), acquisition through the drivers, hardware-timed rigs (daq), whole runs
(run) and the fitter (fit)."""
