"""The run time: plan and execute a run (run.py) — instruments by role, the engine under the supervisor, the
hardware-timed steps on a DAQ — and the interactive sessions on a rig (devices check, manual control, live view)."""
