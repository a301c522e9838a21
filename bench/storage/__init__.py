"""The HDF5 run file: the recorder (writer), the reader, recovery of a crashed run's file, export to CSV/MAT.

Storage knows neither the run time nor the command line (tests/test_layers.py)."""
